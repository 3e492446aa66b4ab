from .cli.start import run

# guarded: worker processes started by spawn (a Dask LocalCluster) re-import the main module
if __name__ == "__main__":
    run()
