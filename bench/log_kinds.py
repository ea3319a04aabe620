"""The MCAP writer thread's CPU per record kind, on a flight's own records (issue #24).

    python bench/log_kinds.py FLIGHT.mcap [--json]

For every kind the live process logs each step, the writer thread's work is redone on the
flight's records: the encoding (:func:`companion.log.encode.encode_json` of the same payload,
:func:`companion.log.encode.mavlink_payload` of the same frame, the PNG crop, the preview's
downscale + JPEG) and the record's write into an LZ4-chunked MCAP (:class:`LeanWriter`, chunk
compression included). Figures: CPU per record (``time.thread_time``), records per step of the
flight, CPU per step, bytes per record before and after the chunk compression. The preview
frame is the largest ``/perception/input`` of the log (a whole frame the detector searched),
encoded with the log's recorded ``[logging]`` preview settings and with ``--preview`` others.
Not counted: the queue hand-off and the per-record bookkeeping of the writer loop (a few us).
CPU figures inflate under load (printed); compare runs made at the same load.
"""

from __future__ import annotations

import argparse
import base64
import io
import json
import os
import sys
import time
import types
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mcap.writer import CompressionType  # noqa: E402

from companion.log.encode import encode_image, encode_json, mavlink_payload  # noqa: E402
from companion.log.mcap_lean import LeanWriter  # noqa: E402
from companion.log.reader import LogMessage, LogReader  # noqa: E402
from companion.log.writer_thread import Sink, downscale  # noqa: E402

Job = Callable[[], bytes]


def _mav_item(m: LogMessage) -> Any:
    d = m.data or {}
    return types.SimpleNamespace(
        raw=base64.b64decode(d.get("raw_b64", "")), fields=d.get("fields") or {},
        t_rx_ns=d.get("t_rx_ns", 0), t_tx_ns=d.get("t_tx_ns", 0), src_sysid=d.get("sysid", 1),
        src_compid=d.get("compid", 1), seq=d.get("seq", 0), signed=d.get("signed", False))


def jobs_of(path: Path, previews: list[tuple[float, int]]) -> tuple[dict[str, list[Job]], int,
                                                                      dict[str, float]]:
    """{kind: one encoder call per record}, the number of steps, records per step by kind."""
    recs: dict[str, list[LogMessage]] = defaultdict(list)
    with LogReader(path) as r:
        for m in r.messages():
            recs[m.topic].append(m)
    steps = max(1, len(recs["/control/step"]))
    jobs: dict[str, list[Job]] = {}
    per_step: dict[str, float] = {}
    mav_in = [_mav_item(m) for t, ms in recs.items() if t.startswith("/mavlink/in/") for m in ms]
    mav_out = [_mav_item(m) for t, ms in recs.items() if t.startswith("/mavlink/out/")
               for m in ms]
    jobs["/mavlink/in/*"] = [lambda it=it: encode_json(mavlink_payload("in", it))
                             for it in mav_in]
    jobs["/mavlink/out/*"] = [lambda it=it: encode_json(mavlink_payload("out", it))
                              for it in mav_out]
    per_step["/mavlink/in/*"], per_step["/mavlink/out/*"] = (len(mav_in) / steps,
                                                             len(mav_out) / steps)
    for t in ("/control/step", "/truth", "/vehicle/pose", "/target/pose"):
        jobs[t] = [lambda d=m.data: encode_json(d) for m in recs[t]]
        per_step[t] = len(recs[t]) / steps
    crops = [m.image for m in recs["/perception/input"] if m.image is not None]
    jobs["/perception/input (png)"] = [
        lambda c=c: encode_image(c, "png", 0, "camera", 75)[1] for c in crops]
    per_step["/perception/input (png)"] = len(crops) / steps
    frame = max(crops, key=lambda c: c.size) if crops else None
    if frame is not None:
        n_prev = len(recs["/camera/image"])
        for scale, quality in previews:
            key = f"/camera/image (jpeg x{scale:g} q{quality})"
            jobs[key] = [lambda s=scale, q=quality: encode_image(
                downscale(frame, s) if s != 1.0 else frame, "jpeg", 0, "camera", q)[1]] * 60
            per_step[key] = n_prev / steps
    return jobs, steps, per_step


def measure(jobs: list[Job]) -> dict[str, float]:
    """CPU per record of encoding + writing ``jobs`` into an LZ4-chunked MCAP in memory."""
    bio = io.BytesIO()
    w = LeanWriter(Sink(bio), chunk_size=1 << 20, compression=CompressionType.LZ4)
    w.start()
    cid = w.register_channel("/t", "json", w.register_schema("x", "jsonschema", b"{}"))
    reps = max(1, 600 // max(1, len(jobs)))
    nbytes = 0
    t0 = time.thread_time()
    for _ in range(reps):
        for job in jobs:
            data = job()
            nbytes += len(data)
            w.add_message(cid, log_time=1, data=data, publish_time=1)
    w.finish()  # type: ignore[no-untyped-call]
    n = reps * len(jobs)
    return {"cpu_us": 1e6 * (time.thread_time() - t0) / n, "kb": nbytes / n / 1e3,
            "kb_in_file": bio.tell() / n / 1e3, "records": n}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("--preview", action="append", default=[], metavar="SCALE:QUALITY",
                    help="another preview setting to measure, e.g. 0.25:75 (repeatable)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    with LogReader(args.log) as r:
        cfg = next((m.data.get("config") or {} for m in r.messages(topics=["/config"])
                    if m.data), {})
    lg = cfg.get("logging", {}) if isinstance(cfg, dict) else {}
    previews = [(float(lg.get("preview_scale", 0.5)), int(lg.get("preview_jpeg_quality", 75)))]
    previews += [(float(s), int(q)) for s, q in (p.split(":") for p in args.preview)]
    load0 = os.getloadavg()[0]
    jobs, steps, per_step = jobs_of(args.log, previews)
    rows = {k: {**measure(v), "per_step": per_step[k]} for k, v in jobs.items() if v}
    for row in rows.values():
        row["cpu_us_per_step"] = row["cpu_us"] * row["per_step"]
    out = {"log": str(args.log), "steps": steps, "load": [load0, os.getloadavg()[0]],
           "preview_rate_hz_recorded": lg.get("preview_rate_hz"), "kinds": rows}
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"{args.log}: {steps} steps; load {load0:.1f} -> {os.getloadavg()[0]:.1f}; "
          f"recorded preview {lg.get('preview_rate_hz')} Hz x{previews[0][0]:g} "
          f"q{previews[0][1]}")
    print(f"{'kind':34s} {'us/record':>10s} {'per step':>9s} {'us/step':>8s} {'kB':>7s} "
          f"{'kB in file':>10s}")
    for k, row in rows.items():
        print(f"{k:34s} {row['cpu_us']:10.1f} {row['per_step']:9.2f} "
              f"{row['cpu_us_per_step']:8.1f} {row['kb']:7.1f} {row['kb_in_file']:10.1f}")
    print("(the previews' us/step at the recorded rate; the sum counts the first preview only)")
    first_prev = next((k for k in rows if k.startswith("/camera/image")), None)
    total = sum(r["cpu_us_per_step"] for k, r in rows.items()
                if not k.startswith("/camera/image") or k == first_prev)
    print(f"writer thread, these kinds: {total:.0f} us per step")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
