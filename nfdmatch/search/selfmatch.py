"""The rule that drops a query's own curve from its matches (``exclude_self``), shared by
every search that offers it (``query``, ``show``, ``Index.search``, the re-ranking)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import functools
import os

from ..curve import STDIN_ID
from ..records import RankedMatch

if TYPE_CHECKING:
    from collections.abc import Callable

__all__ = ["self_rule", "is_self", "drop_self"]


def _curve_key(curve_id: str) -> tuple | None:
    """The file (its device and inode: however the path is spelled, symbolic links
    followed) and curve an id names; None when it names no file here. One stat: a batch
    checks every match of every query."""
    from ..formats import split_selector

    path, selected = split_selector(curve_id)
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino, selected


def self_rule(locate: Callable[[str], str | None] | None = None) -> Callable[[str, str], bool]:
    """``rule(query_id, match_id) -> bool``: whether a match names the query's curve: the
    same id, or the same curve of the same file however the path is spelled (never for
    stdin). ``locate``: id -> a path that opens it here (an index's ids are relative to its
    folder: ``Index.locate``). Each id is resolved once per rule (a batch asks about the
    same ids query after query)."""
    from ..names import decode_name

    where = locate or decode_name  # an id is a file's name encoded (nfdmatch.names)
    stored_key = functools.lru_cache(maxsize=None)(lambda i: _curve_key(where(i)))
    query_key = functools.lru_cache(maxsize=None)(lambda i: _curve_key(decode_name(i)))

    def rule(query_id: str, match_id: str) -> bool:
        if query_id == STDIN_ID:
            return False
        if match_id == query_id:
            return True
        mine = query_key(query_id)
        return mine is not None and stored_key(match_id) == mine

    return rule


def is_self(query_id: str, match_id: str, locate: Callable[[str], str | None] | None = None) -> bool:
    """One question of :func:`self_rule`."""
    return self_rule(locate)(query_id, match_id)


def drop_self(
    query_id: str,
    matches: list[RankedMatch],
    k: int | None,
    locate: Callable[[str], str | None] | None = None,
    rule: Callable[[str, str], bool] | None = None,
) -> list[RankedMatch]:
    """``matches`` (ranked) without those naming the query's curve (:func:`self_rule`;
    ``rule`` one made already, for a batch), ranks renumbered, at most ``k``. The search
    asked for one match more."""
    rule = rule or self_rule(locate)
    kept = [m for m in matches if not rule(query_id, m.id)]
    return [m.replace(rank=rank) for rank, m in enumerate(kept[:k] if k is not None else kept, start=1)]
