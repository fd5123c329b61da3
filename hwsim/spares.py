"""Spare parts kept by shape: what a gone world's Taichi objects leave for the next world of the same shape.

A Taichi data-oriented object's kernels are compiled for its own fields, and the offline cache finds them
again only when a process allocates its fields in the same order as a run before. A process that builds
world after world (the tests, the benchmarks, `hwsim record`) so compiled the same kernels over and over
(docs/benchmarks.md, "Installs"). An object whose owner is gone is kept here under a key of everything its
fields' shapes and its kernels' constants depend on, and handed to the next owner that needs that key.
"""

from __future__ import annotations

import threading
from collections.abc import Hashable
from typing import Generic, TypeVar

K = TypeVar("K", bound=Hashable)
T = TypeVar("T")


class Spares(Generic[K, T]):
    """Objects by key; taken and given from any thread (an owner is let go wherever the garbage collector
    runs)."""

    def __init__(self) -> None:
        self._items: dict[K, list[T]] = {}
        self._lock = threading.Lock()

    def take(self, key: K) -> T | None:
        """A spare of this key, which is no longer here; None when there is none."""
        with self._lock:
            items = self._items.get(key)
            return items.pop() if items else None

    def give(self, key: K, item: T) -> None:
        with self._lock:
            self._items.setdefault(key, []).append(item)
