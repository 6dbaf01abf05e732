"""Results computed from an immutable object, kept exactly as long as the object lives.

A module's `WeakKeyDictionary` whose values refer back to their keys (a contact surface
holds its map, a contact field its contour) keeps every key alive for good: every map and
outline a process ever used stayed in memory, and a `haptic bench grasp` worker grew to
3.6 GB. Kept in the object's own `__dict__`, a result and its object form a cycle that the
collector frees together. A copy sent to another process (pickled) arrives with none: that
process computes its own.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import TypeVar

T = TypeVar("T")


class _Kept(dict):
    """One object's results by key; pickled empty."""

    def __reduce__(self) -> tuple[type, tuple]:
        return (_Kept, ())


def kept(owner: object, key: Hashable, make: Callable[[], T]) -> T:
    """`owner`'s result for `key`, made by `make` the first time it is asked for."""
    results = owner.__dict__.setdefault("_kept", _Kept())
    if key not in results:
        results[key] = make()
    return results[key]
