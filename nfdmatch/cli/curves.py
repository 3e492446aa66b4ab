"""Commands on curve files, without an index: distance, describe, rank, reconstruct."""

from __future__ import annotations

import json
import sys

import click

from .common import (EXIT_ERROR, EXIT_PARTIAL, descriptor_options, handle_errors, input_format_option,
                     match_columns, matching_options, output_option, report_errors, write_rows)
from .group import main


@main.command()
@click.argument("curve_a", metavar="A")
@click.argument("curve_b", metavar="B")
@matching_options
@descriptor_options
@input_format_option
@click.option("--format", "output_format", type=click.Choice(["text", "json"]), default="text",
              show_default=True, help="Output format on stdout.")
@handle_errors
def distance(curve_a, curve_b, method, strict_direction, mirror, samples, harmonics, scale,
             input_format, output_format):
    """Similarity distance between two curves A and B, and the alignment of B onto A.

    A and B are files (FILE#I for curve I of a multi-curve file). The distance is 0 for
    the same shape whatever its position, size, orientation, start vertex, sampling
    and (unless --strict-direction) traversal direction.

    \b
    Example:
      nfdmatch distance sample_curves/library/trefoil.csv sample_curves/queries/trefoil-posed.obj --format json
    """
    from ..formats import read_curve
    from ..matching import distance as match_distance

    a = read_curve(curve_a, format=input_format)
    b = read_curve(curve_b, format=input_format)
    m = match_distance(a, b, samples=samples, harmonics=harmonics, scale=scale, method=method,
                       direction="strict" if strict_direction else "invariant", mirror=mirror)
    record = m.to_dict()
    if output_format == "json":
        click.echo(json.dumps({"a": a.id, "b": b.id, **record}, indent=2))
    else:
        click.echo(f"distance\t{m.distance:.10g}")
        click.echo(f"shift\t{m.shift:.6f}")
        click.echo(f"reversed\t{str(m.reversed).lower()}")
        click.echo(f"mirrored\t{str(m.mirrored).lower()}")
        click.echo(f"scale\t{m.scale:.10g}")
        click.echo("rotation\t" + json.dumps([[round(v, 12) for v in row] for row in record["rotation"]]))
        click.echo("translation\t" + json.dumps([round(v, 12) for v in record["translation"]]))
        click.echo(f"method\t{m.method}")


@main.command()
@click.argument("files", nargs=-1, required=True, metavar="FILE...")
@descriptor_options
@input_format_option
@click.option("--format", "output_format", type=click.Choice(["csv", "tsv", "json", "jsonl"]), default="csv",
              show_default=True, help="Output format on stdout.")
@handle_errors
def describe(files, samples, harmonics, scale, input_format, output_format):
    """Print the normalized Fourier descriptors of every curve in FILE....

    One row per curve: id, parameters, centroid and scale (input units), whether the
    limit plane is degenerate, then the normalized coefficients A_k for
    k = +1..+K, -1..-K: columns k+1_x_re, k+1_x_im, ..., k-K_z_im.
    FILE#I describes one curve of a multi-curve file; a bad file is reported on
    stderr and skipped (exit 3).

    \b
    Example:
      nfdmatch describe sample_curves/library/*.csv --harmonics 8 > descriptors.csv
    """
    from ..descriptors import descriptors_batch, validate_parameters
    from ..sources import read_all

    validate_parameters(samples, harmonics, scale)
    curves, errors = read_all(files, format=input_format)
    report_errors(errors)
    failed = len(errors)
    batch = descriptors_batch(curves, samples=samples, harmonics=harmonics, scale=scale)
    rows = [_descriptor_row(batch.row(i, c.id)) for i, c in enumerate(curves)]
    if not rows and failed:
        sys.exit(EXIT_ERROR)
    if output_format in ("json", "jsonl"):
        columns = ["id", "samples", "harmonics", "scale", "scale_value", "centroid", "plane_degenerate",
                   "frequencies", "coefficients"]
        write_rows(rows, columns, output_format)
    else:
        flat = [_flatten_descriptor_row(r) for r in rows]
        columns = list(flat[0]) if flat else ["id"]
        write_rows(flat, columns, output_format)
    if failed:
        click.echo(f"{failed} of {len(files)} inputs failed", err=True)
        sys.exit(EXIT_PARTIAL)


@main.command()
@click.argument("query_spec", metavar="QUERY")
@click.argument("sources", nargs=-1, required=True, metavar="SOURCE...")
@click.option("--top", type=click.IntRange(min=1), default=10, show_default=True,
              help="Number of matches to list.")
@click.option("--max-distance", type=click.FloatRange(min=0), default=None,
              help="Only list matches at most this far.")
@click.option("--glob", "glob_pattern", default=None, help="Only files in folders whose name matches, e.g. '*.csv'.")
@click.option("--details", is_flag=True, help="Add the columns shift, reversed, mirrored.")
@matching_options
@descriptor_options
@input_format_option
@output_option(help_extra=" (default: a table on a terminal, CSV otherwise)")
@handle_errors
def rank(query_spec, sources, top, max_distance, glob_pattern, details, method, strict_direction, mirror,
         samples, harmonics, scale, input_format, output_format):
    """Rank the curves in SOURCE... (files or folders) by similarity to QUERY, without an index.

    QUERY is one curve (FILE or FILE#I). Folders are searched recursively for files with
    a known extension (hidden files skipped). Files that cannot be read are named on
    stderr and skipped (exit 3). Rows: query, rank, match, distance.

    \b
    Example:
      nfdmatch rank sample_curves/queries/trefoil-posed.obj sample_curves/library --top 5
    """
    from ..formats import read_curve
    from ..search import rank_curves
    from ..sources import find_curve_files, read_all

    query = read_curve(query_spec, format=input_format)
    files = find_curve_files(sources, glob=glob_pattern)
    curves, errors = read_all(files, format=input_format)
    report_errors(errors)
    if not curves and errors:
        sys.exit(EXIT_ERROR)
    ranked = rank_curves(query, curves, top=top, max_distance=max_distance, samples=samples,
                         harmonics=harmonics, scale=scale, method=method,
                         direction="strict" if strict_direction else "invariant", mirror=mirror)
    columns = match_columns(details)
    write_rows([{"query": query.id, **row} for row in ranked], columns, output_format)
    if errors:
        click.echo(f"{len(errors)} of {len(files)} files could not be read", err=True)
        sys.exit(EXIT_PARTIAL)



@main.command()
@click.argument("curve_spec", metavar="FILE")
@click.option("--harmonics", "-k", type=click.IntRange(min=1), required=True,
              help="Harmonics K kept: frequencies +-1..+-K.")
@click.option("--output", "-o", required=True, type=click.Path(dir_okay=False),
              help="The curve file to write; its extension picks the format (csv, obj, vtk, vtp, vtu).")
@click.option("--points", "-m", type=click.IntRange(min=3, max=10_000_000), default=None,
              help="Vertices of the rebuilt curve [default: the samples].")
@click.option("--samples", "-n", type=click.IntRange(min=3), default=None,
              help="Arc-length samples of the transform [default: max(128, 4K)].")
@click.option("--normalized", is_flag=True,
              help="Write the normalized curve (centred, unit scale, limit plane on z = 0), not the input pose.")
@input_format_option
@click.option("--output-format", "curve_format", default=None,
              help="Write this curve format whatever OUT's extension (csv, obj, vtk, vtp, vtu).")
@output_option(help_extra=" for the summary rows (default: a table on a terminal, CSV otherwise)")
@handle_errors
def reconstruct(curve_spec, harmonics, output, points, samples, normalized, input_format, curve_format,
                output_format):
    """Rebuild the curve(s) in FILE from their first K harmonics: what the descriptor sees.

    The rebuilt curve keeps the input's position, size and orientation (unless
    --normalized), and is written to OUT in the format of its extension (a multi-curve
    FILE gives a multi-curve OUT; CSV holds one curve, so select it with FILE#I). Rows on
    stdout: curve, harmonics, vertices, distance (from the rebuilt curve to the input,
    default matching parameters).

    \b
    Example:
      nfdmatch reconstruct sample_curves/library/knotess/5_2.csv -k 4 -o 5_2-k4.vtp
    """
    from ..curve import Curve
    from ..descriptors import descriptors, reconstruct as rebuild
    from ..formats import write_curves
    from ..matching import distance
    from ..sources import read_all

    n = samples if samples is not None else max(128, 4 * harmonics)
    if 2 * harmonics >= n:
        raise click.BadParameter(f"harmonics ({harmonics}) must be below samples/2 ({n}/2)",
                                 param_hint="--harmonics")
    curves, errors = read_all([curve_spec], format=input_format)
    if errors:
        raise errors[0]
    rebuilt, rows = [], []
    for curve in curves:
        d = descriptors(curve, samples=n, harmonics=harmonics)
        pts = rebuild(d, points=points, normalized=normalized)
        rebuilt.append(Curve(pts, id=f"{curve.id} K={harmonics}"))
        rows.append({"curve": curve.id, "harmonics": harmonics, "vertices": len(pts),
                     "distance": None if normalized else float(distance(curve, pts).distance)})
    write_curves(output, rebuilt, format=curve_format)
    columns = ["curve", "harmonics", "vertices"] + ([] if normalized else ["distance"])
    write_rows(rows, columns, output_format)
    click.echo(f"wrote {output}", err=True)


def _descriptor_row(d) -> dict:
    freqs, coeffs = d.band()
    return {
        "id": d.id, "samples": d.samples, "harmonics": d.harmonics, "scale": d.scale_mode,
        "scale_value": float(d.scale), "centroid": [float(v) for v in d.centroid],
        "plane_degenerate": bool(d.plane_degenerate),
        "frequencies": [int(f) for f in freqs],
        # per frequency, per axis x, y, z: [real, imaginary]
        "coefficients": [[[float(c.real), float(c.imag)] for c in row] for row in coeffs],
    }


def _flatten_descriptor_row(row: dict) -> dict:
    flat = {k: row[k] for k in ("id", "samples", "harmonics", "scale", "scale_value", "plane_degenerate")}
    flat.update({f"centroid_{ax}": v for ax, v in zip("xyz", row["centroid"])})
    for f, coeff in zip(row["frequencies"], row["coefficients"]):
        for ax, (re, im) in zip("xyz", coeff):
            flat[f"k{f:+d}_{ax}_re"] = re
            flat[f"k{f:+d}_{ax}_im"] = im
    return flat

