"""The replay's command comparison: a quaternion and its negative are one attitude; anything
non-finite is never identical."""

from __future__ import annotations

import math

import pytest

from companion.replay import ReplayError, _quat_diff


def test_quaternion_difference_is_up_to_sign() -> None:
    q = [0.93, 0.01, -0.02, 0.36]
    assert _quat_diff(q, q) == 0.0
    assert _quat_diff(q, [-v for v in q]) == 0.0
    assert _quat_diff(q, [0.93, 0.01, -0.02, 0.36 + 2e-6]) == pytest.approx(2e-6)
    assert _quat_diff([1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]) == 1.0


def test_non_finite_or_malformed_commands_are_never_identical() -> None:
    q = [1.0, 0.0, 0.0, 0.0]
    assert _quat_diff(q, [math.nan, 0.0, 0.0, 0.0]) == math.inf
    assert _quat_diff([math.inf, 0.0, 0.0, 0.0], q) == math.inf
    with pytest.raises(ReplayError):
        _quat_diff(q, [1.0, 0.0, 0.0])


def test_the_comparison_reads_arrays_and_large_finite_values_alike() -> None:
    import numpy as np

    q = [0.93, 0.01, -0.02, 0.36]
    assert _quat_diff(q, np.array(q)) == 0.0
    assert _quat_diff(np.array(q), [-v for v in q]) == 0.0
    # finite components whose sum overflows are still compared, not called non-finite
    big = [1e308, 1e308, 0.0, 0.0]
    assert _quat_diff(big, big) == 0.0
    assert _quat_diff(big, [1e308, 1e308, 0.0, 1.0]) == 1.0
