"""Seeded generators and the delay line the emulator's latencies are built from (camera frames,
telemetry datagrams): pure, every call takes the time explicitly."""

from __future__ import annotations

import collections
import math
from collections.abc import Iterator
from typing import Generic, TypeVar

import numpy as np

__all__ = ["DelayLine", "rngs"]

T = TypeVar("T")


def rngs(seed: int, n: int, salt: int = 0) -> list[np.random.Generator]:
    """``n`` independent generators derived from ``seed`` (any int) and a per-use ``salt``."""
    ss = np.random.SeedSequence([seed % 2**32, salt])
    return [np.random.default_rng(s) for s in ss.spawn(n)]


class DelayLine(Generic[T]):
    """Items in delivery order, each with the time (s) it is due. ``push`` keeps FIFO order:
    an item is never due before the one pushed ahead of it (a link does not reorder)."""

    def __init__(self) -> None:
        self._q: collections.deque[tuple[float, T]] = collections.deque()
        self._last_due_s = -math.inf

    def push(self, due_s: float, item: T) -> float:
        """Queue ``item``; returns its due time (pushed back behind the previous item)."""
        due = max(due_s, self._last_due_s)
        self._last_due_s = due
        self._q.append((due, item))
        return due

    def pop_due(self, now_s: float) -> Iterator[T]:
        """Yield (and remove) every item due at or before ``now_s``, in order."""
        while self._q and self._q[0][0] <= now_s + 1e-9:
            yield self._q.popleft()[1]

    @property
    def next_due_s(self) -> float:
        return self._q[0][0] if self._q else math.inf

    def __len__(self) -> int:
        return len(self._q)
