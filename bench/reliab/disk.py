"""The MCAP writer on a bad disk, and what ``fsync`` costs: the control loop's logging calls
must not wait for the disk.

A 20 Hz loop in this process makes the logging calls the companion's control step makes (a
1000 x 1000 camera frame, the step record, poses, a few MAVLink messages) into a real
:class:`~companion.log.writer.McapLogger`, and times those calls (``perf_counter``) and the
loop's period. Disks:

- ``normal``: a file on the working disk;
- ``full``: a tmpfs of a few MB that fills during the run (needs root to mount; otherwise
  ``/dev/full``, where every write fails with ENOSPC from the start);
- ``slow``: a FIFO drained by a reader throttled to ``slow_bytes_per_s``;
- ``fsync-interval`` / ``fsync-close`` / ``fsync-never``: the normal disk with each
  ``logging.fsync`` policy (the writer thread's time in ``os.fsync`` is reported).
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from bench.reliab.common import ProbeResult, load_avg
from companion.log.writer import McapLogger


def _frame(rng: np.random.Generator) -> np.ndarray:
    img = np.full((1000, 1000), 90, np.uint8)
    img[::8, :] = 120  # a ground texture PNG does not flatten to nothing
    img[400:600, 380:620] = 230
    img += rng.integers(0, 6, img.shape, dtype=np.uint8)
    return img


def loop_with_logger(lg: McapLogger, duration_s: float, rate_hz: float = 20.0,
                     seed: int = 0) -> dict[str, Any]:
    """Run the loop; per-iteration time inside the logging calls and the loop periods (ms)."""
    rng = np.random.default_rng(seed)
    frames = [_frame(rng) for _ in range(4)]
    period = 1.0 / rate_hz
    call_ms: list[float] = []
    call_cpu_ms: list[float] = []
    periods: list[float] = []
    cpu0 = time.thread_time()
    t_next = time.perf_counter()
    t_prev = None
    n = int(duration_s * rate_hz)
    rec = {"t_s": 0.0, "perception": {"status": "ok", "corners_px": [[1.0, 2.0]] * 4},
           "eta_e": [0.1] * 7, "u": [0.0] * 4, "rmpc": {"u_pred": [[0.0] * 4] * 16,
                                                      "eta_pred": [[0.0] * 7] * 17}}
    for i in range(n):
        now = time.perf_counter()
        if t_prev is not None:
            periods.append((now - t_prev) * 1e3)
        t_prev = now
        t_ns = time.monotonic_ns()
        t0, tc0 = time.perf_counter(), time.thread_time()
        lg.log_image("/camera/image", t_ns, frames[i % len(frames)], "png")
        lg.log("/control/step", t_ns, dict(rec, t_s=i * period), schema="companion.ControllerStep")
        for k in range(6):
            lg.log(f"/mavlink/in/M{k}", t_ns, {"fields": {"x": float(i), "k": k}},
                   schema="companion.Json")
        lg.log_pose("/vehicle/pose", t_ns, "ned", (0.0, 0.0, -3.0), (1.0, 0.0, 0.0, 0.0))
        call_ms.append((time.perf_counter() - t0) * 1e3)
        call_cpu_ms.append((time.thread_time() - tc0) * 1e3)
        t_next += period
        time.sleep(max(0.0, t_next - time.perf_counter()))
    cpu = time.thread_time() - cpu0
    c = np.asarray(call_ms)
    cc = np.asarray(call_cpu_ms)
    p = np.asarray(periods)
    return {
        "iterations": n,
        "log_calls_ms": {"p50": float(np.percentile(c, 50)), "p99": float(np.percentile(c, 99)),
                         "max": float(c.max())},
        "log_calls_cpu_ms": {"p50": float(np.percentile(cc, 50)),
                             "p99": float(np.percentile(cc, 99)), "max": float(cc.max())},
        "period_ms": {"p50": float(np.percentile(p, 50)), "p99": float(np.percentile(p, 99)),
                      "max": float(p.max())},
        "loop_cpu_s": cpu,
    }


@contextlib.contextmanager
def _tmpfs(size_mb: int) -> Iterator[Path | None]:
    d = Path(tempfile.mkdtemp(prefix="rel-full-"))
    ok = os.geteuid() == 0 and subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", "tmpfs", str(d)],
        capture_output=True).returncode == 0
    try:
        yield d if ok else None
    finally:
        if ok:
            subprocess.run(["umount", str(d)], capture_output=True)
        with contextlib.suppress(OSError):
            d.rmdir()


@contextlib.contextmanager
def _slow_fifo(bytes_per_s: float) -> Iterator[tuple[Path, dict[str, int]]]:
    d = Path(tempfile.mkdtemp(prefix="rel-slow-"))
    fifo = d / "log.mcap"
    os.mkfifo(fifo)
    got = {"bytes": 0}
    stop = threading.Event()

    def reader() -> None:
        with open(fifo, "rb", buffering=0) as f:
            chunk = max(1, int(bytes_per_s / 20))
            t_next = time.monotonic()
            while True:
                b = f.read(chunk)
                if not b:
                    return
                got["bytes"] += len(b)
                t_next += len(b) / bytes_per_s
                if not stop.is_set():
                    time.sleep(max(0.0, t_next - time.monotonic()))

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    try:
        yield fifo, got
    finally:
        stop.set()  # drain what is left at full speed so the writer can close
        th.join(timeout=60)
        fifo.unlink(missing_ok=True)
        d.rmdir()


def one_disk(kind: str, work: Path, duration_s: float, full_mb: int = 6,
             slow_bytes_per_s: float = 200_000.0, max_pending_mb: int = 64) -> dict[str, Any]:
    """Run the loop against one disk ``kind``; loop figures plus the logger's counters."""
    fsync = kind.split("-", 1)[1] if kind.startswith("fsync-") else "interval"
    with contextlib.ExitStack() as es:
        extra: dict[str, Any] = {}
        if kind == "full":
            d = es.enter_context(_tmpfs(full_mb))
            path = (d / "log.mcap") if d is not None else Path("/dev/full")
            extra["device"] = f"tmpfs {full_mb} MB" if d is not None else "/dev/full"
        elif kind == "slow":
            path, got = es.enter_context(_slow_fifo(slow_bytes_per_s))
            extra["device"] = f"FIFO read at {slow_bytes_per_s / 1e3:.0f} kB/s"
        else:
            path = work / f"{kind}.mcap"
            extra["device"] = "working disk"
        lg = McapLogger(path, chunk_size=1 << 20, flush_interval_s=1.0, queue_size=4096,
                        max_pending_image_bytes=max_pending_mb << 20, compression="lz4",
                        fsync=fsync)
        lg.open()
        t0 = time.perf_counter()
        fig = loop_with_logger(lg, duration_s)
        t_close = time.perf_counter()
        lg.close(raise_on_failure=False)
        st = lg.stats
        fig.update(extra)
        fig.update(written=st.written, dropped=st.dropped, enqueued=st.enqueued,
                   images_dropped=lg.images_dropped,
                   failure=None if lg.failure is None else repr(lg.failure)[:120],
                   close_s=time.perf_counter() - t_close, wall_s=t_close - t0,
                   fsync_policy=fsync, fsync_count=lg.fsync_count,
                   fsync_time_s=lg.fsync_time_s)
        if kind == "slow":
            fig["bytes_read"] = got["bytes"]
        if path.exists() and path.is_file() and kind != "full":
            fig["file_mb"] = path.stat().st_size / 1e6
    return fig


def run_disk(out: Path, duration_s: float = 20.0) -> list[ProbeResult]:
    out.mkdir(parents=True, exist_ok=True)
    load0 = load_avg()
    res = {k: one_disk(k, out, duration_s) for k in ("normal", "full", "slow")}
    base = res["normal"]["log_calls_ms"]
    rows = []
    for k in ("full", "slow"):
        r = res[k]
        lc = r["log_calls_ms"]
        cpu, bcpu = r["log_calls_cpu_ms"], res["normal"]["log_calls_cpu_ms"]
        # wall times swing with the machine's load: the criterion is the loop thread's CPU
        ok = (r["dropped"] > 0 and r["iterations"] == res["normal"]["iterations"]
              and cpu["p99"] <= 3.0 * bcpu["p99"] + 1.0)
        rows.append(ProbeResult(
            probe=f"disk {k} ({r['device']})",
            inputs=f"{r['iterations']} loop iterations at 20 Hz ({duration_s:.0f} s), "
                   f"{r['enqueued'] + r['dropped']} log items",
            result=(f"logging calls CPU p50/p99 {cpu['p50']:.2f}/{cpu['p99']:.2f} ms (normal "
                    f"disk {bcpu['p50']:.2f}/{bcpu['p99']:.2f}), wall p50/p99/max "
                    f"{lc['p50']:.2f}/{lc['p99']:.2f}/{lc['max']:.2f} ms (normal "
                    f"{base['p50']:.2f}/{base['p99']:.2f}/{base['max']:.2f}); loop period "
                    f"max {r['period_ms']['max']:.0f} ms (normal "
                    f"{res['normal']['period_ms']['max']:.0f}); writer: "
                    f"{r['failure'] or 'no failure'}"),
            passed=ok,
            data_lost=f"{r['dropped']} items dropped and counted ({r['images_dropped']} frames)"
                      f", {r['written']} written",
            figures={"disk": r, "normal": res["normal"], "load": load0},
            wall_s=r["wall_s"],
            cpu_s=r["loop_cpu_s"],
        ))
    return rows


def run_fsync(out: Path, duration_s: float = 20.0) -> ProbeResult:
    out.mkdir(parents=True, exist_ok=True)
    load0 = load_avg()
    res = {p: one_disk(f"fsync-{p}", out, duration_s) for p in ("interval", "close", "never")}
    parts = []
    for p, r in res.items():
        per = r["fsync_time_s"] / r["fsync_count"] * 1e3 if r["fsync_count"] else 0.0
        parts.append(f"{p}: {r['fsync_count']} fsyncs, {r['fsync_time_s'] * 1e3:.0f} ms in "
                     f"total ({per:.1f} ms each, writer thread), log calls p99 "
                     f"{r['log_calls_ms']['p99']:.2f} ms")
    return ProbeResult(
        probe="fsync policy cost (logging.fsync)",
        inputs=f"3 policies x {duration_s:.0f} s at 20 Hz with 1000 x 1000 PNG frames",
        result="; ".join(parts),
        passed=all(r["failure"] is None for r in res.values()),
        data_lost="power loss: <= flush_interval_s (1 s) with 'interval'; up to the whole "
                  "unsynced page cache with 'close'/'never'",
        figures={"policies": res, "load": load0},
        wall_s=sum(r["wall_s"] for r in res.values()),
        cpu_s=sum(r["loop_cpu_s"] for r in res.values()),
    )


if __name__ == "__main__":
    import json

    o = Path("out/reliability/disk")
    print(json.dumps([r.to_json() for r in run_disk(o, 10.0)] + [run_fsync(o, 10.0).to_json()],
                     indent=2, default=str))
