"""Progress bars for the long-running commands (``demo``, ``replay``, ``report``): tqdm on
stderr when it is a terminal, silent otherwise (logs, CI, tests)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from tqdm import tqdm

# no monitor thread: replay forks its perception worker, best done from a single thread
tqdm.monitor_interval = 0


def bar(total: float | None, desc: str, unit: str = "it", **kw: Any) -> Any:
    """A tqdm bar (disabled when stderr is not a terminal)."""
    return tqdm(total=total, desc=desc, unit=unit, disable=None, dynamic_ncols=True,
                leave=True, **kw)


def step_callback(desc: str, unit: str = "step") -> tuple[Any, Callable[[int, int], None]]:
    """(bar, callback(done, total)) for functions that report progress as counts."""
    b = bar(None, desc, unit)

    def update(done: int, total: int) -> None:
        if b.total != total:
            b.total = total
            b.refresh()
        b.update(done - b.n)

    return b, update
