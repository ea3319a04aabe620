"""Perception timing and accuracy at the paper's 1000 x 1000 px.

Scenes come from the test renderer (tests/companion/test_perception.py: textured ground,
dark box sides, bright top, exact area coverage) over random poses (1.5-5 m, tilt <= 0.3 rad,
any yaw). Times are ``perf_counter`` around one call on a mono8 image, after one warm-up call.

    python bench/perception.py [--poses 100] [--seed 1] [--json]
    python bench/perception.py --flight LOG.mcap [--frames 600] [--json]

``--flight`` times ``Perception.process`` on a flight log's own frames in order, with the
region-of-interest tracking the live process uses (the in-flight case), wall per frame and the
mean CPU (thread time) per frame, which the machine's load inflates far less, and each frame's
worst corner error against the emulator's projected corners (``/truth``) where the log has them.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from companion.camera import FrameHeader, decode_payload, pack_frame  # noqa: E402
from companion.config import load_config  # noqa: E402
from companion.perception import ArucoDetector, Perception, RectangleDetector  # noqa: E402
from tests.companion.test_perception import (  # noqa: E402
    box_level,
    ground,
    pose_ok,
    project,
    render_box,
    render_marker,
    set_error_px,
    to_camera,
)


def _stats(ms: list[float]) -> dict[str, float]:
    a = np.asarray(ms)
    return {
        "median_ms": float(np.median(a)),
        "p95_ms": float(np.percentile(a, 95)),
        "max_ms": float(a.max()),
    }


def _timed(fn: Any, arg: Any) -> tuple[Any, float]:
    t0 = time.perf_counter()
    out = fn(arg)
    return out, 1e3 * (time.perf_counter() - t0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=100)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--flight", type=Path, default=None, help="time a flight log's frames")
    ap.add_argument("--frames", type=int, default=600)
    args = ap.parse_args()
    if args.flight is not None:
        return _flight(args.flight, args.frames, args.json)

    cfg = load_config()
    rng = np.random.default_rng(args.seed)
    rect = RectangleDetector(cfg.target.length_m, cfg.target.width_m)
    aruco = ArucoDetector(cfg.target.aruco_dictionary, cfg.target.aruco_id, cfg.target.aruco_size_m)
    perception = Perception(cfg.camera, cfg.target, track_order=False)

    scenes: list[tuple[np.ndarray, np.ndarray]] = []
    while len(scenes) < args.poses:
        depth = rng.uniform(1.5, 5.0)
        top, bottom = box_level(
            depth,
            rng.uniform(-0.5, 0.5) * depth,
            rng.uniform(-0.5, 0.5) * depth,
            rng.uniform(-math.pi, math.pi),
        )
        phi, theta = rng.uniform(-0.3, 0.3, 2)
        if pose_ok(top, bottom, phi, theta, margin=8):
            scenes.append(render_box(int(rng.integers(10_000)), top, bottom, phi, theta))
    marker_scenes: list[tuple[np.ndarray, np.ndarray]] = []
    while len(marker_scenes) < max(10, args.poses // 4):
        depth = rng.uniform(1.5, 3.0)
        top, _ = box_level(
            depth, *(rng.uniform(-0.3, 0.3, 2) * depth), rng.uniform(-math.pi, math.pi), 0.4, 0.4
        )
        true = project(to_camera(top, *rng.uniform(-0.3, 0.3, 2)))
        if true.min() > 60 and true.max() < 1000 - 61:
            img = ground(int(rng.integers(10_000)))
            render_marker(img, true, cfg.target.aruco_dictionary, cfg.target.aruco_id)
            marker_scenes.append((img, true))
    empty = ground(0)

    rect.detect(scenes[0][0])
    aruco.detect(marker_scenes[0][0])
    out: dict[str, Any] = {
        "image_px": [1000, 1000],
        "cpus": os.cpu_count(),
        "loadavg_1min": os.getloadavg()[0],
        "poses": args.poses,
    }
    t_rect, e_rect = [], []
    for img, true in scenes:
        det, ms = _timed(rect.detect, img)
        t_rect.append(ms)
        e_rect.append(set_error_px(det.corners_px, true) if det is not None else math.inf)
    out["rectangle_detect"] = _stats(t_rect)
    out["rectangle_err_px"] = {"median": float(np.median(e_rect)), "max": float(max(e_rect))}
    out["rectangle_empty_image"] = _stats([_timed(rect.detect, empty)[1] for _ in range(20)])
    t_ar, e_ar = [], []
    for img, true in marker_scenes:
        det, ms = _timed(aruco.detect, img)
        t_ar.append(ms)
        e_ar.append(
            float(np.max(np.linalg.norm(det.corners_px - true, axis=1)))
            if det is not None
            else math.inf
        )
    out["aruco_detect"] = _stats(t_ar)
    out["aruco_err_px"] = {"median": float(np.median(e_ar)), "max": float(max(e_ar))}
    out["perception_process"] = _stats([_timed(perception.process, img)[1] for img, _ in scenes])
    mono = pack_frame(0, 0, scenes[0][0])
    jpeg = pack_frame(0, 0, scenes[0][0], "jpeg")
    for name, rec in (("decode_mono8", mono), ("decode_jpeg", jpeg)):
        decode = functools.partial(decode_payload, FrameHeader.unpack(rec[:32]))
        out[name] = _stats([_timed(decode, rec[32:])[1] for _ in range(30)])
    out["opencv"] = cv2.__version__

    if args.json:
        print(json.dumps(out))
        return 0
    print(f"perception at 1000 x 1000 px, {args.poses} poses, load {out['loadavg_1min']:.2f}")
    for key in (
        "rectangle_detect",
        "rectangle_empty_image",
        "aruco_detect",
        "perception_process",
        "decode_mono8",
        "decode_jpeg",
    ):
        s = out[key]
        print(
            f"  {key:24s} median {s['median_ms']:6.2f} ms  p95 {s['p95_ms']:6.2f}  "
            f"max {s['max_ms']:6.2f}"
        )
    for key in ("rectangle_err_px", "aruco_err_px"):
        print(f"  {key:24s} median {out[key]['median']:.3f} px  max {out[key]['max']:.3f} px")
    return 0


def _flight(path: Path, n: int, as_json: bool) -> int:
    from companion.log.reader import LogReader
    from companion.replay_inputs import _Canvas

    cfg = load_config()
    frames = []
    truth: list[Any] = []  # the emulator's projected top corners per frame (None if absent)
    with LogReader(path, verify=False) as r:
        true_px = {d["frame_seq"]: d.get("top_corners_px")
                   for d in (m.data or {} for m in r.messages(topics=["/truth"]))
                   if d.get("frame_seq") is not None}
        if any(c.topic == "/perception/input" for c in r.channels):
            # crops of what perception read, pasted back where they were (docs/reference/logging.md)
            crops = {}
            canvas = _Canvas()
            for m in r.messages(topics=["/perception/input", "/control/step"]):
                if m.topic == "/perception/input":
                    crops[m.log_time_ns] = m.image
                    continue
                inp = (m.data or {}).get("input")
                img = crops.pop(inp["log_time_ns"], None) if inp else None
                if img is not None:
                    frames.append(canvas.paste(img, inp["x0"], inp["y0"], inp["width"],
                                               inp["height"]).copy())
                    truth.append(true_px.get((m.data or {}).get("frame_seq")))
                if len(frames) >= n:
                    break
        else:  # logs written before crops: every frame whole
            for m in r.messages(topics=["/camera/image"]):
                if m.image is not None:
                    frames.append(m.image)
                if len(frames) >= n:
                    break
    perception = Perception(cfg.camera, cfg.target)
    times = []
    found = []
    cpu0 = time.thread_time()
    for img in frames:
        res, dt = _timed(perception.process, img)
        times.append(dt)
        found.append(res.corners_px)
    cpu_ms = 1e3 * (time.thread_time() - cpu0) / max(len(frames), 1)
    ok = sum(c is not None for c in found)
    # the worst corner against the projected true corners after the best one-to-one matching
    # (the order is the detector's business), on frames with both
    errs = [set_error_px(c, np.asarray(t)) for c, t in zip(found, truth, strict=False)
            if c is not None and t is not None]
    out = {"frames": len(frames), "detected": ok, "roi_hits": perception.roi_hits,
           "perception_process": _stats(times), "cpu_ms_per_frame": cpu_ms,
           "loadavg_1min": os.getloadavg()[0]}
    if errs:
        out["corner_err_px"] = {"frames": len(errs), "median": float(np.median(errs)),
                                "max": float(max(errs))}
    if as_json:
        print(json.dumps(out))
        return 0
    s = out["perception_process"]
    print(f"{path}: {len(frames)} flight frames, {ok} detected, {perception.roi_hits} in the "
          f"region of interest, load {out['loadavg_1min']:.2f}")
    print(f"  perception_process       median {s['median_ms']:6.2f} ms  p95 {s['p95_ms']:6.2f}  "
          f"max {s['max_ms']:6.2f}; CPU {cpu_ms:.2f} ms per frame (thread time, wall "
          "figures grow with the load)")
    if errs:
        e = out["corner_err_px"]
        print(f"  worst corner vs the projected truth: median {e['median']:.4f} px, max "
              f"{e['max']:.4f} px over {e['frames']} frames")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
