"""The reliability suite: attacks on the link, the process and the disk, with figures.

    python bench/reliability.py            # everything (~1-2 h on 2 quiet cores, soak included)
    python bench/reliability.py --quick    # short versions (a few minutes)
    python bench/reliability.py --soak-json out/reliability/soak/soak.json   # reuse a soak

Runs every probe of ``bench/reliab/`` against the real emulator and companion processes on
loopback (and the real MCAP writer), then writes ``docs/reference/reliability.md``: one row per
probe (inputs tried, result, data lost, bad commands sent: must be 0), the date, the machine and its
load. The short versions of the same probes are tests (``tests/reliability/``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench.reliab.common import ProbeResult, load_avg  # noqa: E402
from bench.reliab.report import write_report  # noqa: E402


def _mavsdk(out: Path) -> ProbeResult:
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                        "tests/sim/test_mavsdk.py"], cwd=ROOT, capture_output=True, text=True,
                       timeout=600, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    tail = (p.stdout.strip().splitlines() or ["?"])[-1]
    return ProbeResult(probe="MAVSDK flies the unsigned emulator",
                       inputs="tests/sim/test_mavsdk.py (connect, arm, offboard attitude)",
                       result=tail, passed=p.returncode == 0, wall_s=time.monotonic() - t0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short versions of every probe")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "reliability")
    ap.add_argument("--doc", type=Path, default=ROOT / "docs" / "reference" / "reliability.md")
    ap.add_argument("--soak-json", type=Path, default=None,
                    help="use this soak result (written by bench/reliab/soak.py) instead of "
                         "running the soak")
    ap.add_argument("--only", default="", help="comma-separated probe names (debugging)")
    ap.add_argument("--impaired-duration", type=float, default=None,
                    help="simulated seconds of each impaired/clean flight (default 251, "
                         "quick 30)")
    ap.add_argument("--kills", type=int, default=None, help="kill -9 repetitions (20; quick 3)")
    a = ap.parse_args()
    q = a.quick
    out = a.out / ("quick" if q else "full")
    from bench.reliab.disk import run_disk, run_fsync
    from bench.reliab.flood import run_flood
    from bench.reliab.impaired import run_impaired
    from bench.reliab.kill9 import run_kill9
    from bench.reliab.signing import run_signing
    from bench.reliab.soak import run_soak, soak_partial
    from bench.reliab.stall import run_stall

    def soak() -> list[ProbeResult]:
        if a.soak_json is not None:
            if a.soak_json.exists():
                return [ProbeResult(**json.loads(a.soak_json.read_text()))]
            # the soak (bench/reliab/soak.py) is still flying: its figures so far
            return [soak_partial(a.soak_json.parent)]
        return [run_soak(out / "soak", 120.0 if q else 7200.0)]

    probes: dict[str, Callable[[], list[ProbeResult]]] = {
        "flood": lambda: [run_flood(out / "flood", 100_000, duration_s=60.0 if q else 90.0,
                                    flood_at_s=2.0)],
        "flood-realtime": lambda: [run_flood(out / "flood-rt", 100_000, duration_s=40.0,
                                             flood_at_s=5.0, realtime=True)],
        "signing": lambda: [run_signing(out / "signing", 20.0 if q else 40.0)],
        "mavsdk": lambda: [_mavsdk(out)],
        "impaired": lambda: [run_impaired(out / "impaired", a.impaired_duration
                                          or (30.0 if q else 251.0))],
        "stall": lambda: [run_stall(out / "stall")],
        "disk": lambda: run_disk(out / "disk", 8.0 if q else 20.0),
        "fsync": lambda: [run_fsync(out / "disk", 8.0 if q else 20.0)],
        "kill9": lambda: [run_kill9(out / "kill9", a.kills or (3 if q else 20))],
        "soak": soak,
    }
    only = [s for s in a.only.split(",") if s]
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    load0 = load_avg()
    results: list[ProbeResult] = []
    for name, fn in probes.items():
        if only and name not in only:
            continue
        print(f"[reliability] {name} ... (load {load_avg()})", flush=True)
        try:
            rows = fn()
        except Exception as e:  # a probe that crashes is a failed row, not a lost suite
            rows = [ProbeResult(probe=name, inputs="-", result=f"probe crashed: {e!r}",
                                passed=False)]
        for r in rows:
            print(f"  {'PASS' if r.passed else 'FAIL'} {r.probe}: {r.result}", flush=True)
        results.extend(rows)
        (out / "results.json").parent.mkdir(parents=True, exist_ok=True)
        (out / "results.json").write_text(json.dumps([r.to_json() for r in results],
                                                      indent=2, default=str))
    meta = {"started": started, "finished": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "machine": _machine(), "load_before": load0, "load_after": load_avg(),
            "command": "python " + " ".join(
                [str(Path(sys.argv[0]).relative_to(ROOT)) if Path(sys.argv[0]).is_absolute()
                 else sys.argv[0], *sys.argv[1:]])}
    write_report(a.doc, results, meta)
    print(f"[reliability] wrote {a.doc}")
    return 0 if all(r.passed for r in results) else 1


def _machine() -> str:
    cpu = "?"
    try:
        for ln in Path("/proc/cpuinfo").read_text().splitlines():
            if ln.startswith("model name"):
                cpu = ln.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return (f"{platform.node()}: {os.cpu_count()} x {cpu}, {mem:.0f} GiB, "
            f"{platform.system()} {platform.release()}, Python {platform.python_version()}")


if __name__ == "__main__":
    raise SystemExit(main())
