"""Camera models against hand-written projection formulas and OpenCV round trips."""

from __future__ import annotations

import numpy as np
import pytest

from ruslam.data.camera import Camera

EUROC_CAM0 = Camera(752, 480, 458.654, 457.296, 367.215, 248.375,
                    dist=[-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05])
HARBOR = Camera(640, 512, 256.214, 256.571, 330.685, 261.372,
                dist=[-0.0626187, 0.0174982, -0.0102171, 0.00198907], model="fisheye")


def _points(n=50, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-0.4, 0.4, n), rng.uniform(1.0, 3.0, n)])


def test_pinhole_without_distortion_is_K_projection():
    cam = Camera(640, 480, 500.0, 400.0, 320.0, 240.0)
    uv = cam.project(np.array([[0.2, -0.1, 2.0]]))
    assert np.allclose(uv, [[320 + 500 * 0.1, 240 - 400 * 0.05]])
    assert np.allclose(cam.K, [[500, 0, 320], [0, 400, 240], [0, 0, 1]])


def test_radtan_projection_matches_formula_and_undistortion_inverts_it():
    X = _points()
    k1, k2, p1, p2 = EUROC_CAM0.dist
    x, y = X[:, 0] / X[:, 2], X[:, 1] / X[:, 2]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    expected = np.column_stack([458.654 * xd + 367.215, 457.296 * yd + 248.375])
    uv = EUROC_CAM0.project(X)
    assert np.allclose(uv, expected, atol=1e-6)
    ideal = np.column_stack([458.654 * x + 367.215, 457.296 * y + 248.375])
    assert np.abs(EUROC_CAM0.undistort_points(uv) - ideal).max() < 1e-3
    assert np.abs(uv - ideal).max() > 5  # the distortion is real, so the round trip is not trivial


def test_fisheye_projection_matches_kannala_brandt_and_inverts():
    X = _points(seed=1)
    a, b = X[:, 0] / X[:, 2], X[:, 1] / X[:, 2]
    r = np.hypot(a, b)
    th = np.arctan(r)
    k1, k2, k3, k4 = HARBOR.dist
    thd = th * (1 + k1 * th**2 + k2 * th**4 + k3 * th**6 + k4 * th**8)
    expected = np.column_stack([256.214 * thd / r * a + 330.685, 256.571 * thd / r * b + 261.372])
    uv = HARBOR.project(X)
    assert np.allclose(uv, expected, atol=1e-6)
    ideal = np.column_stack([256.214 * a + 330.685, 256.571 * b + 261.372])
    assert np.abs(HARBOR.undistort_points(uv) - ideal).max() < 1e-3


def test_contains_uses_pixel_borders():
    cam = Camera(10, 8, 5, 5, 4.5, 3.5)
    assert cam.contains(np.array([[-0.4, 0], [9.4, 7.4], [-0.6, 0], [3, 7.6]])).tolist() == [True, True, False, False]


def test_bad_calibrations_raise_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="4 coefficients"):
        Camera(640, 480, 1, 1, 0, 0, dist=[0.1, 0.1, 0, 0, 0], model="fisheye")
    with pytest.raises(ValueError, match="model"):
        Camera(640, 480, 1, 1, 0, 0, model="omni")
    with pytest.raises(FileNotFoundError, match="nope.yaml"):
        Camera.from_yaml(tmp_path / "nope.yaml")
    (tmp_path / "bad.yaml").write_text("model: pinhole\nwidth: 640\n")
    with pytest.raises(ValueError, match="intrinsics"):
        Camera.from_yaml(tmp_path / "bad.yaml")
    (tmp_path / "garbage.yaml").write_text("a: [1, 2\n")
    with pytest.raises(ValueError, match="not valid YAML"):
        Camera.from_yaml(tmp_path / "garbage.yaml")


def test_yaml_round_trip(tmp_path):
    import yaml

    (tmp_path / "c.yaml").write_text(yaml.safe_dump(HARBOR.to_dict()))
    cam = Camera.from_yaml(tmp_path / "c.yaml")
    assert cam.model == "fisheye" and np.allclose(cam.K, HARBOR.K) and np.allclose(cam.dist, HARBOR.dist)


def test_orbslam3_settings_of_aqualoc(shared_data):
    folder = shared_data / "trajectories" / "aqualoc_groundtruth"
    harbor = Camera.from_yaml(folder / "ORB_SLAM3_AQUALOC__AQUALOC_Harbor.yaml")
    assert harbor.model == "fisheye" and (harbor.width, harbor.height) == (640, 512)
    assert np.allclose(harbor.dist, HARBOR.dist) and harbor.fx == 256.214
    archaeo = Camera.from_yaml(folder / "ORB_SLAM3_AQUALOC__AQUALOC_Archaeological.yaml")
    assert archaeo.model == "pinhole" and (archaeo.width, archaeo.height) == (968, 608)
    assert np.isclose(archaeo.dist[0], -0.207478) and archaeo.cx == 481.444
