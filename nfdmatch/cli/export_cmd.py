"""`nfdmatch index export`: the stored descriptors as CSV, JSON lines or NumPy's npz."""

from __future__ import annotations

import sys

import click

from .index_cmds import index
from .options import format_option, index_option, output_option
from .output import resolve_format, write_rows


@index.command("export")
@index_option
@format_option(("csv", "jsonl", "npz"), help_extra=" [default: by the extension of -o, else csv]")
@output_option(help="The file to write (.csv, .jsonl or .npz), whole and only on success [default: stdout].")
def index_export(index_path: str, output_format: str | None, output: str | None) -> None:
    """Export the stored descriptors and poses of every curve, for use without h5py.

    Per curve: id, file, the index's samples, harmonics and scale_mode, then scale and
    centroid (input units), rotation (3 x 3, as in nfdmatch.Descriptors), plane_degenerate
    and the normalized coefficients of frequencies +1..+K (x, y, z; those of -k are their
    complex conjugates). CSV flattens them into columns (centroid_x, rotation_01,
    k+1_x_re, ...); JSONL nests them; NPZ holds the arrays ids (n,), files (n,), scale (n,),
    plane_degenerate (n,), centroid (n, 3), rotation (n, 3, 3), coefficients (n, K, 3)
    complex128, frequencies (K,) and the parameters.

    \b
    Example:
      nfdmatch index export --index demo.h5 -o demo.npz
    """
    import io

    import numpy as np

    from ..index import open_index

    fmt = resolve_format(output_format, output, ("csv", "jsonl", "npz"), terminal="csv", piped="csv")
    if fmt == "npz" and output is None and sys.stdout.isatty():
        raise click.UsageError("npz is binary: give -o FILE.npz (or redirect stdout)")
    with open_index(index_path) as idx:
        rows = idx.read_rows(
            0, idx.n_curves, ["coefficients", "rotation", "centroid", "scale", "plane_degenerate", "file"]
        )
        ids = idx.ids()
        paths = [r.path for r in idx.files()]
        params = {"samples": idx.samples, "harmonics": idx.harmonics, "scale_mode": idx.scale_mode}
    files = [paths[i] for i in rows["file"]]
    frequencies = np.arange(1, params["harmonics"] + 1)
    if fmt == "npz":
        buf = io.BytesIO()
        np.savez_compressed(
            buf,
            ids=np.array(ids, dtype=str),
            files=np.array(files, dtype=str),
            scale=rows["scale"],
            plane_degenerate=rows["plane_degenerate"],
            centroid=rows["centroid"],
            rotation=rows["rotation"],
            coefficients=rows["coefficients"],
            frequencies=frequencies,
            **{k: np.array(v) for k, v in params.items()},
        )
        _deliver_bytes(buf.getvalue(), output)
        return
    records = []
    for i, curve_id in enumerate(ids):
        records.append(
            {
                "id": curve_id,
                "file": files[i],
                **params,
                "scale": float(rows["scale"][i]),
                "plane_degenerate": bool(rows["plane_degenerate"][i]),
                "centroid": rows["centroid"][i].tolist(),
                "rotation": rows["rotation"][i].tolist(),
                "frequencies": frequencies.tolist(),
                "coefficients": [[[float(c.real), float(c.imag)] for c in row] for row in rows["coefficients"][i]],
            }
        )
    if fmt == "jsonl":
        columns = list(records[0]) if records else ["id"]
        write_rows(records, columns, "jsonl", output, names=("id", "file"))
        return
    flat = []
    for r in records:
        row = {k: r[k] for k in ("id", "file", "samples", "harmonics", "scale_mode", "scale", "plane_degenerate")}
        row.update({f"centroid_{ax}": v for ax, v in zip("xyz", r["centroid"])})
        row.update({f"rotation_{i}{j}": r["rotation"][i][j] for i in range(3) for j in range(3)})
        for f, coeff in zip(r["frequencies"], r["coefficients"]):
            for ax, (re, im) in zip("xyz", coeff):
                row[f"k{f:+d}_{ax}_re"] = re
                row[f"k{f:+d}_{ax}_im"] = im
        flat.append(row)
    write_rows(flat, list(flat[0]) if flat else ["id"], "csv", output, names=("id", "file"))


def _deliver_bytes(data: bytes, output: str | None) -> None:
    from .options import detail
    from .output import write_if_changed

    if output is None:  # stdout (not a terminal: checked before)
        sys.stdout.buffer.write(data)
        sys.stdout.flush()
        return
    detail(f"wrote {output}" if write_if_changed(output, data) else f"{output} unchanged")
