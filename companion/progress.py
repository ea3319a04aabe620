"""Progress bars for the long-running commands (``demo``, ``replay``, ``report``): tqdm on
stderr when it is a terminal, silent otherwise (logs, CI, tests; tqdm is then not even
imported: ~0.05-0.1 s of a replay's start-up)."""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any


def bar(total: float | None, desc: str, unit: str = "it", **kw: Any) -> Any:
    """A tqdm bar (disabled when stderr is not a terminal)."""
    from tqdm import tqdm

    # no monitor thread: replay forks its perception worker, best done from a single thread
    tqdm.monitor_interval = 0
    return tqdm(total=total, desc=desc, unit=unit, disable=None, dynamic_ncols=True,
                leave=True, **kw)


class _Silent:
    """What :func:`step_callback` returns instead of a bar nobody sees."""

    def close(self) -> None:
        pass


def step_callback(desc: str, unit: str = "step") -> tuple[Any, Callable[[int, int], None]]:
    """(bar, callback(done, total)) for functions that report progress as counts."""
    if not _terminal():
        return _Silent(), lambda done, total: None
    b = bar(None, desc, unit)

    def update(done: int, total: int) -> None:
        if b.total != total:
            b.total = total
            b.refresh()
        b.update(done - b.n)

    return b, update


def _terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # no stderr, or a closed one
        return False
