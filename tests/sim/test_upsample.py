"""The ground's compiled 2x upsampling (sim_bridge/camera/upsample.py) gives ``cv2.resize``'s
pixels (INTER_LINEAR) on random images of many sizes and on rendered ground, and without the
kernel the same call falls back to ``cv2.resize``."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from sim_bridge.camera import upsample

needs_kernel = pytest.mark.skipif(upsample.kernel() is None,
                                  reason="no C compiler or not x86-64: cv2.resize is used")


def _ref(src: np.ndarray) -> np.ndarray:
    h, w = src.shape
    return cv2.resize(src, (2 * w, 2 * h), interpolation=cv2.INTER_LINEAR)


@needs_kernel
def test_kernel_gives_cv2_resize_pixels() -> None:
    fn = upsample.kernel()
    assert fn is not None
    rng = np.random.default_rng(11)
    sizes = [(500, 500), (480, 640), (1, 2), (3, 2), (2, 17), (31, 33), (64, 48)]
    sizes += [(int(rng.integers(1, 90)), int(rng.integers(2, 90))) for _ in range(40)]
    for h, w in sizes:
        for lo, hi in ((0, 256), (40, 151), (250, 256), (0, 3)):  # full, ground, extremes
            src = rng.integers(lo, hi, (h, w), dtype=np.uint8)
            np.testing.assert_array_equal(upsample._run(fn, src), _ref(src), f"{h}x{w}")
    # a strided view (a row pitch wider than the row) and the module's entry point
    big = rng.integers(0, 256, (50, 80), dtype=np.uint8)
    view = big[5:45, 7:70]
    np.testing.assert_array_equal(upsample.upsample2x(view), _ref(np.ascontiguousarray(view)))


def test_no_compiler_means_cv2_resize(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(shutil, "which", lambda name: None)
    assert upsample._build(tmp_path) is None
    monkeypatch.setattr(upsample, "kernel", lambda directory=None: None)
    src = np.random.default_rng(1).integers(0, 256, (20, 30), dtype=np.uint8)
    np.testing.assert_array_equal(upsample.upsample2x(src), _ref(src))


@needs_kernel
def test_a_kernel_that_differs_is_refused(tmp_path: Path) -> None:
    """The start-up check catches a wrong kernel (here: the rounding's + 2 removed)."""
    bad = tmp_path / "upsample2x.c"
    bad.write_text(upsample.SOURCE_PATH.read_text().replace(
        "_mm_set1_epi16(2)", "_mm_set1_epi16(0)").replace(
        "_mm256_set1_epi16(2)", "_mm256_set1_epi16(0)").replace("+ y[i] + 2)", "+ y[i])"))
    src_path = upsample.SOURCE_PATH
    try:
        upsample.SOURCE_PATH = bad
        lib = upsample._build(tmp_path)
        assert lib is not None
        assert not upsample._matches(upsample._load(lib))
    finally:
        upsample.SOURCE_PATH = src_path


def test_load_checked_falls_back_at_each_step(tmp_path: Path) -> None:
    """The camera kernels' one loader: no library, an unloadable one, or one that differs
    from what it replaces each give None (the OpenCV / numpy path); only a match is used."""
    def fn(*args: object) -> int:
        return 0

    def bad_load(lib: Path) -> upsample._Kernel:
        raise OSError("not a library")

    lib = tmp_path / "k.so"
    assert upsample.load_checked("t", lambda d: None, lambda p: fn, lambda f: True,
                                 "ref", tmp_path) is None
    assert upsample.load_checked("t", lambda d: lib, bad_load, lambda f: True,
                                 "ref", tmp_path) is None
    assert upsample.load_checked("t", lambda d: lib, lambda p: fn, lambda f: False,
                                 "ref", tmp_path) is None
    assert upsample.load_checked("t", lambda d: lib, lambda p: fn, lambda f: True,
                                 "ref", tmp_path) is fn
