"""The compiled stage loop of the target's motion (``prediction_kernel.c``) computes the Python
loop's numbers bit for bit, and a kernel that does not is refused before its first use."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from companion.core import prediction
from companion.core.prediction_kernel import (
    SOURCE_PATH,
    check_cases,
    first_mismatch,
    motion_kernel,
)
from companion.core.rmpc import RmpcParameterError

HAVE_CC = shutil.which("gcc") is not None or shutil.which("cc") is not None


@pytest.fixture(scope="module")
def kernel():  # type: ignore[no-untyped-def]
    if not HAVE_CC:
        pytest.skip("no C compiler: the Python loop (its own tests in test_prediction*.py)")
    k = motion_kernel(prediction.python_loop)
    assert k is not None, "the kernel did not load or failed its check (see the log)"
    return k


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a).view(np.uint64)


def test_the_kernel_is_the_python_loop_bit_for_bit(kernel) -> None:  # type: ignore[no-untyped-def]
    # cases beyond the load check's own: another seed, more of them, longer horizons
    cases = check_cases(count=2000, seed=7)
    for values, horizon, d in cases:
        (got, finite), want = kernel(values, horizon, d), prediction.python_loop(
            values, horizon, d)
        assert finite
        for g, w in zip(got, want, strict=True):
            assert (g is None) == (w is None)
            if g is not None:
                assert g.shape == w.shape and np.array_equal(_bits(g), _bits(w)), (values, d)
    assert first_mismatch(kernel, prediction.python_loop) == ""


def test_predict_target_motion_through_the_kernel_is_the_python_path(
        kernel, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    args = (np.array([0.8, -0.3, 0.0]), np.array([0.2, 0.1, 0.0]), 0.21, 0.7, 16, 0.05,
            np.array([0.05, -0.02, 0.3]), 1.0)
    monkeypatch.setattr(prediction, "_KERNEL", [kernel])
    via_c = prediction.predict_target_motion(*args)
    monkeypatch.setattr(prediction, "_KERNEL", [None])
    via_py = prediction.predict_target_motion(*args)
    for name in ("v_a_m_s", "vdot_a_m_s2", "psidot_a_rad_s", "disturbance_v_m_s2"):
        a, b = getattr(via_c, name), getattr(via_py, name)
        assert np.array_equal(_bits(a), _bits(b)), name
        assert not a.flags.writeable
    # a non-finite input is refused the same way on both paths
    for k in (kernel, None):
        monkeypatch.setattr(prediction, "_KERNEL", [k])
        with pytest.raises(RmpcParameterError, match="v_a_m_s: not finite"):
            prediction.predict_target_motion(np.array([np.inf, 0.0, 0.0]), *args[1:])


def test_a_kernel_that_differs_is_refused(tmp_path: Path) -> None:
    if not HAVE_CC:
        pytest.skip("no C compiler")
    # the cross-track rate term with the wrong sign: a small difference on turning targets
    wrong = SOURCE_PATH.read_text().replace("w * -vvx", "w * vvx")
    assert wrong != SOURCE_PATH.read_text()
    assert motion_kernel(prediction.python_loop, str(tmp_path), source=wrong) is None
    # and a source that does not compile
    assert motion_kernel(prediction.python_loop, str(tmp_path), source="not C") is None
