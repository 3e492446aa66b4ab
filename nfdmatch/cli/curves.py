"""Commands on curve files, without an index: distance, describe, rank, reconstruct."""

from __future__ import annotations

import json
import os
from typing import TYPE_CHECKING, Any

import click

from ..descriptors import DEFAULT_SAMPLES
from ..errors import NfdError, WriteError
from .inputs import read_inputs, read_one
from .options import (
    check_writable,
    comparison_options,
    descriptor_options,
    elastic_options,
    match_list_options,
    format_option,
    glob_options,
    input_format_option,
    int_option,
    note_inputs,
    nothing_matched,
    output_option,
    refuse_input_as_output,
    rows_format_option,
    say,
)
from .output import deliver, match_columns, match_row, path_speller, resolve_format, write_rows
from .group import main

if TYPE_CHECKING:
    from ..descriptors import Descriptors
    from ..search.stages import ElasticStage
    from .options import Comparison, MatchListing


@main.command()
@click.argument("curve_a", metavar="A")
@click.argument("curve_b", metavar="B")
@click.option(
    "--elastic",
    is_flag=True,
    help="Also the elastic stage's terms at the exact optimum: elastic, statistics and fused (docs/elastic.md).",
)
@comparison_options
@format_option(("text", "json"), help_extra=" [default: by the extension of -o (.json, .txt), else text]")
@output_option()
def distance(
    curve_a: str,
    curve_b: str,
    elastic: bool,
    comparison: Comparison,
    output_format: str | None,
    output: str | None,
) -> None:
    """Similarity distance between two curves A and B, and the alignment of B onto A.

    A and B are files (FILE#I for curve I of a multi-curve file; `-` for stdin). The
    distance is 0 for the same shape whatever its position, size, orientation, start
    vertex, sampling and (unless --strict-direction) traversal direction.

    --elastic adds the elastic stage's terms (docs/elastic.md): the elastic distance (the
    best correspondence that bends, at the exact optimum's start and direction), the
    distance of pose-free shape statistics, and the fused distance `query --elastic` ranks by.

    \b
    Example:
      nfdmatch distance sample_curves/library/trefoil.csv sample_curves/queries/trefoil-posed.obj --format json
    """
    from ..matching import distance as match_distance

    output_format = resolve_format(output_format, output, ("text", "json"), terminal="text", piped="text")
    if curve_a == "-" and curve_b == "-":
        raise click.UsageError("stdin ('-') can be read once: give it for A or B, not both")
    a = read_one(curve_a, comparison.input_format)
    b = read_one(curve_b, comparison.input_format)
    if elastic:
        from ..matching.fused import fused_distance

        m, terms = fused_distance(a, b, **comparison.keywords())
        stage = {key: float(getattr(terms, key)[0]) for key in ("elastic", "statistics", "fused")}
    else:
        m, stage = match_distance(a, b, **comparison.keywords()), {}
    record = {**m.to_dict(), **stage}
    if output_format == "json":
        from ..names import decode_name  # the file names the ids encode, as the row formats write them

        text = json.dumps({"a": decode_name(a.id), "b": decode_name(b.id), **record}, indent=2) + "\n"
    else:
        text = "".join(
            f"{key}\t{value}\n"
            for key, value in [
                ("distance", f"{m.distance:.10g}"),
                *((key, f"{value:.10g}") for key, value in stage.items()),
                ("shift", f"{m.shift:.6f}"),
                ("reversed", str(m.reversed).lower()),
                ("mirrored", str(m.mirrored).lower()),
                ("scale", f"{m.scale:.10g}"),
                ("rotation", json.dumps([[round(v, 12) for v in row] for row in record["rotation"]])),
                ("translation", json.dumps([round(v, 12) for v in record["translation"]])),
                ("method", m.method),
            ]
        )
    deliver(text, output)


@main.command()
@click.argument("files", nargs=-1, required=True, metavar="FILE_OR_FOLDER...")
@glob_options()
@descriptor_options
@input_format_option
@format_option(("csv", "tsv", "json", "jsonl"), help_extra=" [default: by the extension of -o, else csv]")
@output_option()
def describe(
    files: tuple[str, ...],
    glob_pattern: str | None,
    descriptor: dict[str, Any],
    input_format: str | None,
    output_format: str | None,
    output: str | None,
) -> None:
    """Print the normalized Fourier descriptors of every curve in FILE_OR_FOLDER....

    One row per curve: id, parameters, centroid and scale (input units), whether the
    limit plane is degenerate, then the normalized coefficients A_k for
    k = +1..+K, -1..-K: columns k+1_x_re, k+1_x_im, ..., k-K_z_im.
    Folders are searched recursively; FILE#I describes one curve of a multi-curve file.
    A bad input is named on stderr and skipped (exit 3; exit 2 when none could be read).

    \b
    Example:
      nfdmatch describe sample_curves/library/ --harmonics 8 -o descriptors.csv
    """
    from ..descriptors import descriptors_batch, validate_parameters

    fmt = resolve_format(output_format, output, ("csv", "tsv", "json", "jsonl"), terminal="csv")
    validate_parameters(**descriptor)
    inputs = read_inputs(files, glob=glob_pattern, input_format=input_format, progress="reading curves")
    batch = descriptors_batch(inputs.curves, **descriptor)
    rows = [_descriptor_row(batch.row(i, c.id)) for i, c in enumerate(inputs.curves)]
    if fmt in ("json", "jsonl"):
        columns = [
            "id",
            "samples",
            "harmonics",
            "scale",
            "scale_value",
            "centroid",
            "plane_degenerate",
            "frequencies",
            "coefficients",
        ]
        write_rows(rows, columns, fmt, output)
    else:
        flat = [_flatten_descriptor_row(r) for r in rows]
        write_rows(flat, list(flat[0]), fmt, output)
    inputs.finish()


@main.command()
@click.argument("query_spec", metavar="QUERY")
@click.argument("sources", nargs=-1, required=True, metavar="SOURCE...")
@match_list_options("Number of matches to list.", " Of the SOURCE folders.")
@elastic_options
@comparison_options
@rows_format_option
@output_option()
def rank(
    query_spec: str,
    sources: tuple[str, ...],
    listing: MatchListing,
    stage: ElasticStage | None,
    comparison: Comparison,
    output_format: str | None,
    output: str | None,
) -> None:
    """Rank the curves in SOURCE... (files or folders) by similarity to QUERY, without an index.

    QUERY is one curve (FILE, FILE#I or `-`). Folders are searched recursively for files
    with a known extension (hidden files skipped). Inputs that cannot be read are named
    on stderr and skipped (exit 3). Rows: query, rank, match, distance.

    --elastic: the elastic stage (docs/elastic.md): the exact top M ordered by the fused
    distance; adds the columns elastic and fused.

    \b
    Example:
      nfdmatch rank sample_curves/queries/trefoil-posed.obj sample_curves/library --top 5
    """
    from ..search import rank_curves

    output_format = resolve_format(output_format, output)
    query = read_one(query_spec, comparison.input_format)
    inputs = read_inputs(sources, glob=listing.glob, input_format=comparison.input_format, progress="reading curves")
    ranked = rank_curves(query, inputs.curves, **listing.search(), **comparison.keywords(), stage=stage)
    spell = path_speller(listing.paths)
    write_rows(
        [{**match_row(spell(query.id), m), "match": spell(m.id)} for m in ranked],
        match_columns(listing.details, stage),
        output_format,
        output,
        group_by="query",
    )
    inputs.finish()
    nothing_matched(len(ranked))


@main.command()
@click.argument("curve_spec", metavar="FILE")
@click.option(
    "--harmonics", "-k", type=click.IntRange(min=1), required=True, help="Harmonics K kept: frequencies +-1..+-K."
)
@click.option(
    "--output",
    "-o",
    required=True,
    type=click.Path(dir_okay=False),
    help="The curve file to write; its extension picks the format (csv, obj, vtk, vtp, vtu).",
)
@click.option(
    "--points",
    "-m",
    type=click.IntRange(min=3, max=10_000_000),
    default=None,
    help="Vertices of the rebuilt curve [default: the samples].",
)
@int_option(
    "--samples",
    "-n",
    minimum=3,
    help=f"Arc-length samples of the transform [default: max({DEFAULT_SAMPLES}, 4K)].",
)
@click.option(
    "--normalized",
    is_flag=True,
    help="Write the normalized curve (centred, unit scale, limit plane on z = 0), not the input pose.",
)
@input_format_option
@click.option(
    "--output-format",
    "curve_format",
    default=None,
    help="Write this curve format whatever OUT's extension (csv, obj, vtk, vtp, vtu).",
)
@format_option(help_extra=" of the summary rows on stdout (default: a table on a terminal, CSV otherwise)")
def reconstruct(
    curve_spec: str,
    harmonics: int,
    output: str,
    points: int | None,
    samples: int | None,
    normalized: bool,
    input_format: str | None,
    curve_format: str | None,
    output_format: str | None,
) -> None:
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
    from .._io import write_file
    from ..errors import ParameterError, UnknownFormatError
    from ..formats import FORMATS, format_of, write_curves
    from ..reconstruction import reconstruct_curves, reconstruction_samples

    try:
        reconstruction_samples(harmonics, samples)
    except ParameterError as exc:
        raise click.BadParameter(exc.message, param_hint="--harmonics") from None
    try:  # what OUT will be, before any work (a mesh extension is not a curve file to write)
        curve_format = format_of(output, curve_format)
    except UnknownFormatError:
        ext = os.path.splitext(output)[1].lower()
        given = f"--output-format {curve_format!r}" if curve_format else (f"{ext!r}" if ext else "no extension")
        raise click.UsageError(
            f"-o {output}: {given} is not a curve format reconstruct writes; the extension picks one of "
            f"{', '.join(e for exts in FORMATS.values() for e in exts)} (or --output-format {'|'.join(FORMATS)})"
        ) from None
    check_writable(output)
    if curve_spec == "-":
        curves = [read_one("-", input_format)]
    else:
        from ..formats import read_curve, read_curves, split_selector

        path, selected = split_selector(curve_spec)
        curves = (
            [read_curve(curve_spec, format=input_format)]
            if selected is not None
            else read_curves(path, format=input_format)
        )
        note_inputs([path])
    refuse_input_as_output(output)
    rebuilt = reconstruct_curves(curves, harmonics=harmonics, samples=samples, points=points, normalized=normalized)

    def produce(temp: str) -> None:
        try:
            write_curves(temp, [r.curve for r in rebuilt], format=curve_format)
        except NfdError as exc:  # named as OUT, not the temporary file beside it
            if exc.path != str(temp):
                raise
            raise type(exc)(exc.message, path=output, line=exc.line, curve=exc.curve) from None

    try:
        write_file(output, produce)
    except OSError as exc:
        if isinstance(exc, NfdError):
            raise
        raise WriteError(f"cannot write the file ({exc.strerror or exc})", path=output) from None
    rows = [
        {"curve": r.source_id, "harmonics": r.harmonics, "vertices": len(r.curve.points), "distance": r.distance}
        for r in rebuilt
    ]
    write_rows(rows, ["curve", "harmonics", "vertices", "distance"], output_format)
    say(f"wrote {output}")


def _descriptor_row(d: Descriptors) -> dict:
    freqs, coeffs = d.band()
    return {
        "id": d.id,
        "samples": d.samples,
        "harmonics": d.harmonics,
        "scale": d.scale_mode,
        "scale_value": float(d.scale),
        "centroid": [float(v) for v in d.centroid],
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
