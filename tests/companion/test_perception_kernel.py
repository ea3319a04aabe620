"""The compiled "lean2" refinement ([perception] compiled_edges, perception/edges_kernel.py)
against the numpy path it replaces: the same numbers bit for bit (``==``, never a tolerance) on
rendered frames, random and adversarial samplings, edge cases; a kernel broken on purpose fails
these checks; without a compiler (or with the key off) the numpy path runs.
"""

from __future__ import annotations

import ctypes
import functools
import math
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest

from companion.config import load_config
from companion.perception import Perception
from companion.perception.edges_kernel import SOURCE_PATH as KERNEL_SOURCE
from companion.perception.edges_kernel import Lean2Refiner, lean2_kernel, lean2_refiner
from companion.perception.edges_kernel_check import (
    check_frames,
    refine_mismatch,
    same_refinement,
    warp_matches,
)
from companion.perception.edges_lean import LeanSettings
from companion.perception.edges_lean2 import refine_quad_lean2
from companion.perception.pipeline import make_detector
from companion.perception.rectangle import RectangleDetector, RectangleSettings
from tests.companion import test_perception as tp

CFG = load_config()
HAVE_CC = shutil.which("gcc") is not None or shutil.which("cc") is not None


@pytest.fixture(scope="module")
def kernel():  # type: ignore[no-untyped-def]
    if not HAVE_CC:
        pytest.skip("no C compiler: the numpy path (tested below)")
    k = lean2_kernel()
    assert k is not None, "a compiler is here: the kernel must build and pass its load check"
    return k


def _both(gray: np.ndarray, start: np.ndarray, s: LeanSettings, scale: list[float] | None,
          refiner: Lean2Refiner) -> None:
    reads_np = [math.inf, math.inf, -math.inf, -math.inf]
    reads_c = list(reads_np)
    want = refine_quad_lean2(gray, start, s, scale, reads_np)
    got = refiner(gray, start, s, scale, reads_c)
    assert same_refinement(want, got), (want, got)
    assert reads_np == reads_c


def test_the_warp_is_cv2s_on_random_and_adversarial_samplings(kernel) -> None:  # type: ignore[no-untyped-def]
    # 1500 random probes (~1.5 M samples: the detector's 33 x 48 grid and other sizes, which
    # read OpenCV's scalar tail; positions off the image) and 40 adversarial images
    assert warp_matches(kernel.warp_fn, kernel.block, probes=1500, adversarial=40, seed=3)


def test_refinements_are_numpys_bit_for_bit_on_rendered_quads(kernel) -> None:  # type: ignore[no-untyped-def]
    refiner = Lean2Refiner(kernel)
    assert refine_mismatch(refiner, frames=160, seed=5) == ""
    assert refiner.fallbacks == 0 and refiner.calls == 160 * 4
    # the frames exercise both outcomes: refined corners and None (too few profiles)
    outcomes = {refine_quad_lean2(g, q, LeanSettings(), None) is None
                for g, q in check_frames(5, 40)}
    assert outcomes == {True, False}


def test_edge_cases_are_numpys(kernel) -> None:  # type: ignore[no-untyped-def]
    refiner = Lean2Refiner(kernel)
    rng = np.random.default_rng(2)
    quad = np.array([[60.0, 40.0], [140.0, 45.0], [135.0, 100.0], [58.0, 95.0]])
    flat = np.full((150, 200), 90, dtype=np.uint8)  # no crossing in any profile
    noise = rng.integers(0, 256, (150, 200), dtype=np.uint8)  # crossings everywhere, no edge
    low = np.full((150, 200), 100, dtype=np.uint8)
    cv2.fillConvexPoly(low, quad.astype(np.int32), 112)  # 12 grey levels of contrast
    for gray in (flat, noise, low):
        for s in (LeanSettings(), LeanSettings(min_contrast=10.0)):
            for scale in (None, [1.0, 2.0, 3.0, 1.5]):
                _both(gray, quad, s, scale, refiner)
    # a quad at the image's corner: the profiles read off the image (replicated border)
    edge = np.full((120, 160), 80, dtype=np.uint8)
    corner_quad = np.array([[2.0, 1.0], [70.0, 3.0], [68.0, 50.0], [1.0, 48.0]])
    cv2.fillConvexPoly(edge, corner_quad.astype(np.int32), 220)
    for scale in (None, [3.0, 3.0, 3.0, 3.0]):
        _both(edge, corner_quad + 0.7, LeanSettings(), scale, refiner)
    # an edge too short, and a start far off the image
    _both(edge, np.array([[10.0, 10.0], [14.0, 10.0], [14.0, 60.0], [10.0, 60.0]]),
          LeanSettings(), None, refiner)
    _both(edge, corner_quad + 5000.0, LeanSettings(), None, refiner)
    # not row-contiguous (a BGR image's channel): the numpy path, the same numbers
    bgr = np.dstack([edge, edge, edge])
    _both(bgr[:, :, 1], corner_quad + 0.7, LeanSettings(), None, refiner)
    assert refiner.fallbacks == 1


def _flight(frames: list[np.ndarray], compiled: bool) -> list[tuple]:
    cfg = load_config(overrides=[f"perception.compiled_edges={str(compiled).lower()}"])
    perception = Perception(cfg.camera, cfg.target, perception=cfg.perception)
    det = perception.detector
    assert isinstance(det, RectangleDetector)
    assert isinstance(det._lean2, Lean2Refiner) == compiled
    out = []
    for img in frames:
        res = perception.process(img)
        out.append((res.status, res.reason, None if res.corners_px is None
                    else res.corners_px.tolist(), res.quality, det.last_read_box))
    return out


@pytest.mark.parametrize(("noise_std", "blur_sigma_px", "gain"),
                         [(5.0, 0.0, 1.0), (20.0, 0.0, 1.0), (10.0, 1.5, 1.0), (5.0, 1.0, 0.5),
                          (5.0, 1.0, 1.4)])
def test_a_tracked_sequence_is_the_same_with_and_without_the_kernel(
        kernel, noise_std: float, blur_sigma_px: float, gain: float) -> None:  # type: ignore[no-untyped-def]
    """Perception on the suite's rendered box moving ~3 px a frame (tracking, its blob
    search on the first frame and after a jump): every status, corner, quality and read box
    equal."""
    frames = []
    for k in range(24):
        jump = 0.2 if k >= 16 else 0.0
        top, bottom = tp.box_level(2.5, -0.1 + 0.012 * k + jump, 0.05, 0.4 + 0.01 * k)
        img, _ = tp.render_box(7, top, bottom, 0.1, -0.05)
        frames.append(tp.degrade(np.clip(img * gain, 0, 255).astype(np.uint8), noise_std,
                                 blur_sigma_px, seed=k))
    compiled, plain = _flight(frames, True), _flight(frames, False)
    assert [c[0] for c in compiled].count("ok") >= 20
    assert compiled == plain


def _warp_path(kernel, path: int) -> ctypes._CFuncPtr | None:  # type: ignore[no-untyped-def]
    """The kernel's warp through ``path`` (1 software fma, 2 scalar fma, 3 AVX2) as a
    ``lean2_warp``-like function, or None when this CPU lacks it."""
    lib = ctypes.CDLL(str(kernel.library))
    fn = lib.lean2_warp_path
    fn.restype = ctypes.c_int
    vp, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    fn.argtypes = [i32, vp, i64, i32, i32, vp, i32, i32, i32, vp]
    probe = np.zeros((4, 4), dtype=np.uint8)
    out = np.zeros((2, 2), dtype=np.uint8)
    m = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5]])
    if fn(path, probe.ctypes.data, 4, 4, 4, m.ctypes.data, 2, 2, 16, out.ctypes.data) == -2:
        return None
    return functools.partial(fn, path)  # type: ignore[return-value]


def test_a_broken_kernel_fails_the_checks(kernel, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Each change below alters the numbers (an operation rounded otherwise, another
    summation order, another comparison): the checks must see it. The warp's changes are
    made in the path this CPU runs (AVX2, else the scalar body)."""
    src = KERNEL_SOURCE.read_text()
    if _warp_path(kernel, 3) is not None:
        warp_mutations = [
            ("__m256 r = _mm256_fmadd_ps(b, _mm256_sub_ps(f1, f0), f0);",
             "__m256 r = _mm256_add_ps(_mm256_mul_ps(b, _mm256_sub_ps(f1, f0)), f0);"),
            ("__m256 sx = _mm256_fmadd_ps(vm0, fx, vx),",
             "__m256 sx = _mm256_add_ps(_mm256_mul_ps(vm0, fx), vx),"),
            ("sx = __builtin_fmaf(fx, m0, mx) + m2;", "sx = fx * m0 + (mx + m2);")]
    else:
        warp_mutations = [("float r = FMA(b, f1 - f0, f0);", "float r = b * (f1 - f0) + f0;")]
    mutations = [
        *warp_mutations,
        # the analysis and the fits
        ("if (gemv) {", "if (0) {"),
        ("res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));",
         "res = (((r[0] + r[1]) + r[2]) + r[3]) + ((r[4] + r[5]) + (r[6] + r[7]));"),
        ("(contrast >= minc)", "((double)contrast >= g->min_contrast)"),
        ("if (r == 0 || score > best)", "if (r == 0 || score >= best)"),
    ]
    for old, new in mutations:
        assert old in src, old
        broken = lean2_kernel(str(tmp_path), src.replace(old, new))
        if broken is None:  # the load check caught it
            continue
        assert not (warp_matches(broken.warp_fn, broken.block, probes=1500, adversarial=40,
                                 seed=3)
                    and refine_mismatch(Lean2Refiner(broken), frames=160, seed=5) == ""), new


def test_without_a_compiler_the_numpy_path_runs(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv("CC", raising=False)
    src = KERNEL_SOURCE.read_text() + "\n/* not in any cache */\n"
    assert lean2_kernel(str(tmp_path / "cache"), src) is None
    assert not list((tmp_path / "cache").glob("*.so")) if (tmp_path / "cache").exists() else True


def test_the_key_turns_the_kernel_off() -> None:
    off = load_config(overrides=["perception.compiled_edges=false"])
    det = make_detector(off.target, off.perception)
    assert isinstance(det, RectangleDetector) and det._lean2 is refine_quad_lean2
    assert lean2_refiner(False) is refine_quad_lean2
    assert RectangleSettings(compiled=False).compiled is False
    assert load_config().perception.compiled_edges is True  # config/paper.toml
    with pytest.raises(Exception, match="compiled_edges"):
        load_config(overrides=["perception.compiled_edges=3"])


@pytest.mark.parametrize("path", [1, 2, 3])
def test_every_warp_path_is_cv2s(kernel, path: int) -> None:  # type: ignore[no-untyped-def]
    """The software fma, the scalar loop on the fma instruction and AVX2 (a CPU takes the
    first it can run: each must give cv2's bytes; a path this CPU lacks is skipped)."""
    one = _warp_path(kernel, path)
    if one is None:
        pytest.skip(f"warp path {path} is not on this CPU")
    assert warp_matches(one, kernel.block, probes=600, adversarial=15, seed=9)


def test_numpys_blas_is_found_after_casadis_is_loaded() -> None:
    """Once an RMPC is built, CasADi's own OpenBLAS is in the process too, with a plain
    ``cblas_dgemv`` of other roundings: the kernel must still take numpy's (and then pass its
    check), whichever of the two was loaded first (the replay and the tests build the
    controller before the detector)."""
    if not HAVE_CC:
        pytest.skip("no C compiler")
    code = ("from companion.perception.edges_kernel import numpy_dgemv, lean2_kernel\n"
            "{before}\n"
            "print(numpy_dgemv()[1]); print(lean2_kernel() is not None)\n")
    build = ("from companion.config import load_config\n"
             "from companion.core.design import design_terminal\n"
             "from companion.core.rmpc import Rmpc\n"
             "c = load_config(); Rmpc(c.rmpc, c.camera, design_terminal(c.rmpc, c.camera))\n"
             "import re\n"
             "assert any(re.search('casadi.*blas', ln) for ln in open('/proc/self/maps'))")
    out = [subprocess.run([sys.executable, "-c", code.format(before=b)], capture_output=True,
                          text=True, check=True, timeout=120).stdout.split()
           for b in ("", build)]
    assert out[0] == out[1] and out[1][1] == "True", out
