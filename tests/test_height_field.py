"""The height-field crossing search both ray-casters use: first crossing found, misses and starts below reported."""

from __future__ import annotations

import numpy as np
import pytest

from ruslam.data.height_field import first_crossing


@pytest.mark.parametrize("method", ["bisection", "false_position"])
def test_first_crossing_plane_ridge_miss_and_start_below(method):
    """Four rays' gaps: a plane crossed at t = 2; a ridge before that plane; the plane with a march too short to
    reach it; a ray that starts below the surface."""
    t0 = np.zeros(4, np.float32)
    span = np.array([4.0, 4.0, 1.0, 4.0], np.float32)
    ridge = np.array([0.0, 1.5, 0.0, 0.0], np.float32)
    start = np.array([2.0, 2.0, 2.0, -0.5], np.float32)

    def gap(t):
        return (start - t - ridge * np.exp(-((t - 1.0) / 0.3) ** 2)).astype(np.float32)

    t, found = first_crossing(gap, t0, span, samples=12, splits=6, method=method, min_drop=1e-12)
    assert t.dtype == np.float32 and found.tolist() == [True, True, False, False]
    assert abs(t[0] - 2.0) < 1e-5
    fine = np.linspace(0, 2, 200001)
    first = fine[np.argmax(2.0 - fine - 1.5 * np.exp(-((fine - 1.0) / 0.3) ** 2) <= 0)]
    assert 0.5 < first < 1.0 and abs(t[1] - first) < 1e-3
