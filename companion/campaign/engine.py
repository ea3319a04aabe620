"""The campaign's engine: the runs on Dask (``distributed``), a local cluster by default.

Local: a ``LocalCluster`` of ``workers`` worker processes with one thread each (one flight at a
time per worker; a flight is two more processes, the emulator and the companion, which take
turns in lockstep: about one core per flight), on loopback, no dashboard, nothing to set up.
``address``: a running scheduler (``dask scheduler`` + ``dask worker`` on each machine, every
worker with this package installed and the output folder at the same path). Runs already
finished (``result.json`` in their folder) are skipped, so a campaign resumes where it stopped.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from companion import CompanionError
from companion.campaign.runner import finished_result, run_flight
from companion.campaign.scenarios import RunSpec

__all__ = ["EngineStats", "run_campaign"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EngineStats:
    """What one invocation did: runs flown now and skipped (finished before), the workers
    (threads) the engine gave, wall time of the flown part (s), flights per minute."""

    flown: int
    skipped: int
    workers: int
    wall_s: float

    @property
    def flights_per_minute(self) -> float | None:
        return 60.0 * self.flown / self.wall_s if self.flown and self.wall_s > 0 else None


def _error_row(spec: RunSpec, exc: BaseException) -> dict[str, Any]:
    return {"run_id": spec.run_id, "controller": spec.controller, "scenario": spec.scenario,
            "seed": spec.seed, "path": spec.path, "speed_scale": spec.speed_scale,
            "status": "error", "error": f"engine: {type(exc).__name__}: {exc}"[:300]}


def run_campaign(specs: Sequence[RunSpec], workers: int | None = None,
                 address: str | None = None, progress: bool = True, retry_errors: bool = False,
                 on_row: Callable[[dict[str, Any]], None] | None = None,
                 ) -> tuple[list[dict[str, Any]], EngineStats]:
    """Run every spec not finished yet; return all rows (finished before or now, in the order
    of ``specs``) and what this invocation did. A failed run is a row (never an exception);
    the engine only raises if it cannot start."""
    try:
        import distributed
        from tqdm import tqdm
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise CompanionError("campaign: the engine is an optional extra: "
                             "pip install -e '.[campaign]'") from exc
    rows: dict[str, dict[str, Any]] = {}
    pending: list[RunSpec] = []
    for s in specs:
        done = finished_result(s)
        if done is not None and not (retry_errors and done.get("status") != "ok"):
            rows[s.run_id] = done
        else:
            if done is not None:
                os.remove(os.path.join(s.out_dir, "result.json"))
            pending.append(s)
    skipped = len(specs) - len(pending)
    n_workers = workers or os.cpu_count() or 1
    if not pending:
        return [rows[s.run_id] for s in specs], EngineStats(0, skipped, 0, 0.0)
    logging.getLogger("distributed").setLevel(logging.WARNING)  # its INFO is per-worker chatter
    dist: Any = distributed  # untyped library
    Client, LocalCluster, as_completed = dist.Client, dist.LocalCluster, dist.as_completed
    cluster = None
    if address:
        client = Client(address)
    else:
        # the scheduler's HTTP server binds even without a dashboard, on 8787 unless told
        # otherwise: a free port, so a second campaign (or a test beside one) does not collide
        cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                               dashboard_address="127.0.0.1:0", host="127.0.0.1",
                               scheduler_kwargs={"dashboard": False},
                               silence_logs=logging.ERROR)
        client = Client(cluster)
    t0 = time.monotonic()
    try:
        threads = sum(client.nthreads().values())
        log.info("campaign: %d runs to fly (%d finished before) on %d worker thread(s)%s",
                 len(pending), skipped, threads, f" at {address}" if address else "")
        futures = {client.submit(run_flight, s, key=f"flight-{s.run_id}", pure=False): s
                   for s in pending}
        bar = tqdm(total=len(pending), unit="flight", disable=not progress,
                   desc=f"campaign ({threads} workers)")
        try:
            for fut in as_completed(futures):
                spec = futures[fut]
                try:
                    row = fut.result()
                except Exception as exc:  # the worker died (KilledWorker, ...): a row too
                    row = _error_row(spec, exc)
                rows[spec.run_id] = row
                if on_row is not None:
                    on_row(row)
                bar.update(1)
                if row.get("status") != "ok":
                    bar.write(f"{spec.run_id}: {row.get('error')}")
        finally:
            bar.close()
        wall = time.monotonic() - t0
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return ([rows[s.run_id] for s in specs],
            EngineStats(len(pending), skipped, threads, wall))
