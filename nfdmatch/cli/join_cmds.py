"""The whole index against itself: ``pairs`` (near-duplicate pairs) and ``groups`` (their
connected components); the library's :func:`nfdmatch.search.groups.index_pairs` and
:func:`~nfdmatch.search.groups.index_groups`."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import click

from .options import (
    detail,
    index_option,
    int_option,
    matching_options,
    max_distance_option,
    nothing_matched,
    options_bundle,
    output_option,
    rows_format_option,
)
from .output import deliver, progress_bar, resolve_format, write_rows
from .cluster import open_cluster, scheduler_options
from .group import main

if TYPE_CHECKING:
    from collections.abc import Callable

    from ..search.join import JoinStats
    from .options import Packing


@dataclass(frozen=True)
class SelfJoin:
    """What ``pairs`` and ``groups`` join the index against itself by (:func:`_self_join_options`):
    the index (--index), the distance D (--max-distance), the library's matching keywords and
    the cluster (--scheduler, --scheduler-timeout)."""

    index_path: str
    max_distance: float
    matching: dict[str, Any]
    scheduler: str | None
    scheduler_timeout: float


def _self_join_options(own: Callable[[Any], Any]) -> Packing:
    """--index, --max-distance D, the command's ``own`` option (passed through), the matching
    options and the cluster's, passed on as ``join``: a :class:`SelfJoin`."""
    return options_bundle(
        "join",
        SelfJoin,
        index_option,
        max_distance_option(
            required=True,
            metavar="D",
            help="Two curves at most this exact distance apart are a pair (near-duplicates).",
        ),
        own,
        matching_options,
        scheduler_options,
    )


def _work(stats: JoinStats, what: str) -> None:
    detail(
        f"{what}: {stats.rows} curves, {stats.cell_pairs} pairs of cells opened, {stats.bounded} pairs bounded, "
        f"{stats.exact} exact distances; {stats.seconds:.2f} s"
    )


@main.command()
@_self_join_options(
    click.option(
        "--new",
        "new_only",
        is_flag=True,
        help="Only pairs with at least one curve that the index's last build added or recomputed "
        "(a nightly job: what arrived since).",
    )
)
@rows_format_option
@output_option()
def pairs(join: SelfJoin, new_only: bool, output_format: str | None, output: str | None) -> None:
    """List every pair of curves of the index at most D apart, each once (a < b).

    Rows: a, b, distance (the exact distance, sorted by a then b). Computed for the index
    as a whole: its cells against each other, every pair bounded before its exact distance
    is computed, so the list is the one all pairwise distances would give.

    \b
    Examples:
      nfdmatch pairs --index curves.h5 --max-distance 0.05 -o duplicates.csv
      nfdmatch pairs --index curves.h5 --max-distance 0.05 --new --format jsonl
      nfdmatch pairs --index /shared/curves.h5 --max-distance 0.05 --scheduler tcp://head:8786
    """
    from ..search.groups import index_pairs

    found, stats = _joined(index_pairs, "pairs", join, new=new_only)
    _work(stats, f"{len(found)} pairs")
    write_rows(
        [{"a": p.a, "b": p.b, "distance": p.distance} for p in found],
        ["a", "b", "distance"],
        output_format,
        output,
        names=("a", "b"),
    )
    nothing_matched(len(found), f"no pair at most {join.max_distance} apart")


@main.command()
@_self_join_options(
    int_option("--min-size", default=1, help="Only list groups of at least this many curves (2: only the duplicates).")
)
@rows_format_option
@output_option()
def groups(join: SelfJoin, min_size: int, output_format: str | None, output: str | None) -> None:
    """Group the curves of the index into near-duplicate groups.

    A group is a connected component of the pairs at most D apart (`nfdmatch pairs`):
    single linkage, so a chain of near-duplicates is one group even when its ends are far
    apart. Rows, one per curve: id, group (1, 2, ... by the groups' smallest ids), size,
    representative (the member with the smallest total distance to the others, ties by
    id). --format json gives one object per group with its members as a list.

    \b
    Examples:
      nfdmatch groups --index curves.h5 --max-distance 0.05 --min-size 2 -o groups.csv
      nfdmatch groups --index curves.h5 --max-distance 0.05 --format json
    """
    from ..search.groups import index_groups

    members, stats = _joined(index_groups, "groups", join, min_size=min_size)
    _work(stats, f"{len({m.group for m in members})} groups")
    if resolve_format(output_format, output) == "json":
        from ..names import decode_name  # the file names the ids encode, as write_rows writes them

        listed: dict[int, dict] = {}
        for m in members:
            g = listed.setdefault(
                m.group,
                {"group": m.group, "size": m.size, "representative": decode_name(m.representative), "members": []},
            )
            g["members"].append(decode_name(m.id))
        deliver(json.dumps(list(listed.values()), indent=2) + "\n", output)
    else:
        write_rows(
            [{"id": m.id, "group": m.group, "size": m.size, "representative": m.representative} for m in members],
            ["id", "group", "size", "representative"],
            output_format,
            output,
            names=("id", "representative"),
        )
    nothing_matched(len(members), "no group")


def _joined(
    run: Callable[..., tuple[list[Any], JoinStats]], label: str, join: SelfJoin, **options: Any
) -> tuple[list[Any], JoinStats]:
    """``run(index, max_distance, progress=, cluster=, **options)`` (the library's pairs or
    groups) over the open index as ``join`` says (its matching keywords among the options),
    on a cluster when one is named, with a progress bar."""
    from ..index import open_index

    with open_index(join.index_path) as idx:
        cluster = open_cluster(join.scheduler, join.scheduler_timeout) if join.scheduler else None
        progress, finish_bar = progress_bar(label)
        try:
            return run(idx, join.max_distance, progress=progress, cluster=cluster, **options, **join.matching)
        finally:
            finish_bar()
            if cluster is not None:
                cluster.close()
