"""Perception timing and accuracy at the paper's 1000 x 1000 px.

Scenes come from the test renderer (tests/companion/test_perception.py: textured ground,
dark box sides, bright top, exact area coverage) over random poses (1.5-5 m, tilt <= 0.3 rad,
any yaw). Times are ``perf_counter`` around one call on a mono8 image, after one warm-up call.

    python bench/perception.py [--poses 100] [--seed 1] [--json]
    python bench/perception.py --flight LOG.mcap [--frames 600] [--methods lean2,lean2c] [--json]
    python bench/perception.py --cases [--poses 200] [--reps 3] [--where roi,frame] [--json]

``--cases`` compares the rectangle detector's edge methods (``[perception] rectangle_edges``;
``lean2c`` is "lean2" through the compiled kernel, ``lean2`` its numpy path:
"profiles", the detector before 2026-11-28, "lean" and "lean2") on the same frames,
interleaved: CPU per frame (``time.process_time``, single thread, each frame ``--reps`` times)
and the worst corner error per frame (median / p95 / max px) for the clean poses and the
degraded cases (noise, blur, exposure gain) the tests bound, on the region of interest a flight
searches (the corners' box grown by its size on every side; ``--where frame`` or ``roi,frame``
for the whole frame too). A search without a previous detection: the tracking is not in it
(``--flight`` has it).

``--flight`` times ``Perception.process`` on a flight log's own frames in order, with the
region-of-interest tracking the live process uses (the in-flight case), for each edge method
(``[perception] rectangle_edges``) interleaved frame by frame: wall per frame and the CPU
(thread time) per frame (mean, median, p95), which the machine's load inflates far less,
and each frame's worst corner error against the emulator's projected corners (``/truth``)
where the log has them.
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
    degrade,
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


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=100)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--flight", type=Path, default=None, help="time a flight log's frames")
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--methods", default="lean2,lean2c",
                    help="--flight: edge methods, of profiles, lean, lean2 (numpy) and lean2c "
                         "(lean2 through the compiled kernel)")
    ap.add_argument("--cases", action="store_true", help="edge methods on degraded cases")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--where", default="roi",
                    help="--cases: roi, frame or roi,frame (a frame is degraded whole: slower)")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.flight is not None:
        return _flight(args.flight, args.frames, args.json, args.methods.split(","))
    if args.cases:
        return _cases(args.poses, args.seed, args.reps, args.json, args.where.split(","))
    out = _poses(args.poses, args.seed)
    if args.json:
        print(json.dumps(out))
        return 0
    _print_poses(out)
    return 0


def _box_scenes(rng: np.random.Generator, poses: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``poses`` rendered boxes (image, true corners) at random poses the detector can see."""
    scenes: list[tuple[np.ndarray, np.ndarray]] = []
    while len(scenes) < poses:
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
    return scenes


def _marker_scenes(rng: np.random.Generator, count: int,
                   cfg: Any) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` ground images with the ArUco marker (image, true corners) well inside."""
    marker_scenes: list[tuple[np.ndarray, np.ndarray]] = []
    while len(marker_scenes) < count:
        depth = rng.uniform(1.5, 3.0)
        top, _ = box_level(
            depth, *(rng.uniform(-0.3, 0.3, 2) * depth), rng.uniform(-math.pi, math.pi), 0.4, 0.4
        )
        true = project(to_camera(top, *rng.uniform(-0.3, 0.3, 2)))
        if true.min() > 60 and true.max() < 1000 - 61:
            img = ground(int(rng.integers(10_000)))
            render_marker(img, true, cfg.target.aruco_dictionary, cfg.target.aruco_id)
            marker_scenes.append((img, true))
    return marker_scenes


def _poses(poses: int, seed: int) -> dict[str, Any]:
    """The random-pose figures: each detector's time and corner error, the pipeline's time,
    the frame decoders' time."""
    cfg = load_config()
    rng = np.random.default_rng(seed)
    rect = RectangleDetector(cfg.target.length_m, cfg.target.width_m)
    aruco = ArucoDetector(cfg.target.aruco_dictionary, cfg.target.aruco_id, cfg.target.aruco_size_m)
    perception = Perception(cfg.camera, cfg.target, track_order=False)
    scenes = _box_scenes(rng, poses)
    marker_scenes = _marker_scenes(rng, max(10, poses // 4), cfg)
    empty = ground(0)

    rect.detect(scenes[0][0])
    aruco.detect(marker_scenes[0][0])
    out: dict[str, Any] = {
        "image_px": [1000, 1000],
        "cpus": os.cpu_count(),
        "loadavg_1min": os.getloadavg()[0],
        "poses": poses,
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
    return out


def _print_poses(out: dict[str, Any]) -> None:
    print(f"perception at 1000 x 1000 px, {out['poses']} poses, load {out['loadavg_1min']:.2f}")
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


def _flight_frames(path: Path, n: int) -> tuple[list[Any], list[Any]]:
    """Up to ``n`` of a flight log's frames in order and, per frame, the emulator's projected
    top corners (None where the log has none)."""
    from companion.log.reader import LogReader
    from companion.replay_inputs import _Canvas

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
    return frames, truth


def _flight(path: Path, n: int, as_json: bool, methods: list[str]) -> int:
    cfg = load_config()
    frames, truth = _flight_frames(path, n)
    from companion.perception.rectangle import RectangleSettings

    # every edge method on the same frames, interleaved frame by frame (the machine's load
    # drifts alike for all), each with its own region-of-interest tracking; "lean2c" is
    # "lean2" through the compiled kernel (docs/reference/perception.md), "lean2" numpy's
    runs = {m: Perception(cfg.camera, cfg.target, detector=RectangleDetector(
        cfg.target.length_m, cfg.target.width_m, settings=RectangleSettings(
            edges=m.rstrip("c"), compiled=m == "lean2c"))) for m in methods}
    times: dict[str, list[float]] = {m: [] for m in runs}
    found: dict[str, list[Any]] = {m: [] for m in runs}
    bits: dict[str, list[Any]] = {m: [] for m in runs}  # corners and quality, to compare
    cpu: dict[str, list[float]] = {m: [] for m in runs}
    for img in frames:
        for m, perception in runs.items():
            c0 = time.thread_time()
            res, dt = _timed(perception.process, img)
            cpu[m].append(1e3 * (time.thread_time() - c0))
            times[m].append(dt)
            found[m].append(res.corners_px)
            bits[m].append((None if res.corners_px is None else res.corners_px.tolist(),
                            res.quality, res.status))
    out: dict[str, Any] = {"frames": len(frames), "loadavg_1min": os.getloadavg()[0]}
    if "lean2" in bits and "lean2c" in bits:
        out["lean2c_identical_frames"] = sum(
            a == b for a, b in zip(bits["lean2"], bits["lean2c"], strict=True))
    for m, perception in runs.items():
        # the worst corner against the projected true corners after the best one-to-one
        # matching (the order is the detector's business), on frames with both
        errs = [set_error_px(c, np.asarray(t)) for c, t in zip(found[m], truth, strict=False)
                if c is not None and t is not None]
        r: dict[str, Any] = {
            "detected": sum(c is not None for c in found[m]), "roi_hits": perception.roi_hits,
            "perception_process": _stats(times[m]),
            "cpu_ms_per_frame": float(np.mean(cpu[m])) if cpu[m] else math.nan,
            "cpu_ms": _stats(cpu[m]) if cpu[m] else {}}
        if errs:
            r["corner_err_px"] = {"frames": len(errs), "median": float(np.median(errs)),
                                  "p95": float(np.percentile(errs, 95)),
                                  "max": float(max(errs))}
        out[m] = r
    if as_json:
        print(json.dumps(out))
        return 0
    _print_flight(path, out, list(runs))
    return 0


def _print_flight(path: Path, out: dict[str, Any], methods: list[str]) -> None:
    print(f"{path}: {out['frames']} flight frames, load {out['loadavg_1min']:.2f}")
    if "lean2c_identical_frames" in out:
        print(f"  lean2c (compiled) == lean2 (numpy), corners, quality and status bit for bit: "
              f"{out['lean2c_identical_frames']} of {out['frames']} frames")
    for m in methods:
        r = out[m]
        s = r["perception_process"]
        c = r["cpu_ms"]
        print(f"  edges = {m!r}: {r['detected']} detected, {r['roi_hits']} in the region of "
              f"interest; CPU {r['cpu_ms_per_frame']:.2f} ms per frame (thread time; median "
              f"{c['median_ms']:.2f}, p95 {c['p95_ms']:.2f}); wall median {s['median_ms']:.2f} "
              f"ms, p95 {s['p95_ms']:.2f} (grows with the load)")
        if "corner_err_px" in r:
            e = r["corner_err_px"]
            print(f"    worst corner vs the projected truth: median {e['median']:.4f} px, p95 "
                  f"{e['p95']:.4f}, max {e['max']:.4f} px over {e['frames']} frames")


# (name, noise std, blur sigma px, exposure gain) of the degraded cases the tests bound
# (tests/companion/test_perception.py, test_perception_exposure.py)
CASES = [("clean", 0.0, 0.0, 1.0), ("noise 10", 10.0, 0.0, 1.0), ("noise 20", 20.0, 0.0, 1.0),
         ("blur 1.0", 0.0, 1.0, 1.0), ("blur 1.5", 0.0, 1.5, 1.0),
         ("noise 10 + blur 1.5", 10.0, 1.5, 1.0), ("blur 2.0", 0.0, 2.0, 1.0),
         ("gain 0.5, noise 5, blur 1", 5.0, 1.0, 0.5), ("gain 1.4, noise 5, blur 1", 5.0, 1.0, 1.4)]


def _case_frames(poses: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    return _box_scenes(np.random.default_rng(seed), poses)


def _roi(img: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from companion.perception.pipeline import roi_box
    x0, y0, x1, y1 = roi_box(true, img.shape[1], img.shape[0])
    return img[y0:y1, x0:x1], true - np.array([x0, y0], dtype=np.float64)


def _cases(poses: int, seed: int, reps: int, as_json: bool, places: list[str]) -> int:
    """Every edge method on the same frames, interleaved frame by frame (the machine's load
    drifts alike for all): CPU per frame and worst corner error per frame."""
    from companion.perception.pipeline import limit_opencv_threads
    from companion.perception.rectangle import EDGE_METHODS, RectangleSettings

    limit_opencv_threads()
    cfg = load_config()
    # "lean2": numpy's path, "lean2c": the same through the compiled kernel
    dets = {m: RectangleDetector(cfg.target.length_m, cfg.target.width_m,
                                 settings=RectangleSettings(edges=m.rstrip("c"),
                                                            compiled=m == "lean2c"))
            for m in (*EDGE_METHODS, "lean2c")}
    scenes = _case_frames(poses, seed)
    out: dict[str, Any] = {"poses": poses, "reps": reps, "loadavg_1min": os.getloadavg()[0],
                           "cases": {}}
    for name, noise, blur, gain in CASES:
        for where in places:
            cpu = {m: 0.0 for m in dets}
            errs: dict[str, list[float]] = {m: [] for m in dets}
            for i, (img, true) in enumerate(scenes):
                t = true
                if where == "roi":  # degraded after the crop (>= 40 px around the target)
                    img, t = _roi(img, true)
                if gain != 1.0:
                    img = np.clip(np.rint(img * gain), 0, 255).astype(np.uint8)
                if noise or blur:
                    img = degrade(img, noise, blur, seed=i)
                for m, det in dets.items():
                    t0 = time.process_time()
                    for _ in range(reps):
                        found = det.detect(img)
                    cpu[m] += time.process_time() - t0
                    errs[m].append(set_error_px(found.corners_px, t) if found is not None
                                   else math.inf)
            for m in dets:
                e = np.asarray(errs[m])
                fin = e[np.isfinite(e)]
                out["cases"][f"{name} | {where} | {m}"] = {
                    "cpu_ms": 1e3 * cpu[m] / (reps * len(scenes)),
                    "found": int(fin.size), "frames": len(scenes),
                    "median_px": float(np.median(fin)) if fin.size else math.nan,
                    "p95_px": float(np.percentile(fin, 95)) if fin.size else math.nan,
                    "max_px": float(fin.max()) if fin.size else math.nan}
    out["loadavg_1min_end"] = os.getloadavg()[0]
    if as_json:
        print(json.dumps(out))
        return 0
    print(f"rectangle detector, {poses} poses x {len(CASES)} cases, CPU per frame "
          f"(process_time, single thread, {reps} reps), worst corner error per frame; load "
          f"{out['loadavg_1min']:.2f} -> {out['loadavg_1min_end']:.2f}")
    print(f"  {'case':28s} {'where':5s} {'edges':8s} {'CPU ms':>7s} {'found':>7s} "
          f"{'median':>7s} {'p95':>7s} {'max px':>7s}")
    for key, r in out["cases"].items():
        name, where, m = key.split(" | ")
        print(f"  {name:28s} {where:5s} {m:8s} {r['cpu_ms']:7.3f} "
              f"{r['found']:3d}/{r['frames']:<3d} {r['median_px']:7.3f} {r['p95_px']:7.3f} "
              f"{r['max_px']:7.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
