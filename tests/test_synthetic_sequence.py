"""The synthetic seafloor sequence: exact geometry, the loop, determinism, EuRoC read-back, turbid levels."""

from __future__ import annotations

import numpy as np
import pytest

from ruslam.data.synthetic_sequence import (
    DEPTH_SCALE,
    SeafloorConfig,
    circuit_poses,
    make_seafloor,
    pixel_rays,
    render,
    synthetic_sequence,
)

TINY = dict(num_frames=12, width=160, height=120, focal=112.5, texture_res=512, height_res=300)


@pytest.fixture(scope="module")
def stereo_seq(tmp_path_factory):
    return synthetic_sequence("clear", stereo=True, cache_dir=tmp_path_factory.mktemp("cache"), progress=False, **TINY)


def _depth(seq, i, c):
    import cv2

    path = seq.image_paths[i][c].parent.parent.parent / f"depth{c}" / "data" / seq.image_paths[i][c].name
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64) / DEPTH_SCALE


def test_read_back_through_euroc_reader(stereo_seq):
    cfg = SeafloorConfig(stereo=True, **TINY)
    assert len(stereo_seq) == 12 and stereo_seq.stereo and stereo_seq.name == "seafloor_clear"
    assert np.allclose(stereo_seq.groundtruth.poses, circuit_poses(cfg), atol=1e-8)
    assert np.allclose(stereo_seq.groundtruth.timestamps, stereo_seq.timestamps)
    assert np.allclose(stereo_seq.T_cam0_cam1[:3, 3], [0.12, 0, 0])
    left, right = stereo_seq.load(3)
    assert left.shape == (120, 160, 3) and left.dtype == np.uint8 and left.std() > 10


def test_depth_is_metric_and_consistent_across_the_stereo_pair(stereo_seq):
    """A left pixel's 3-D point (range along its ray) reprojects into the right image onto the same 3-D point."""
    cam = stereo_seq.cameras[0]
    rays = pixel_rays(cam).reshape(-1, 3).astype(np.float64)
    d0, d1 = _depth(stereo_seq, 5, 0).ravel(), _depth(stereo_seq, 5, 1)
    X0 = rays * d0[:, None]  # left camera frame
    X1 = X0 - stereo_seq.T_cam0_cam1[:3, 3]  # right camera frame (pure translation along x)
    uv = cam.project(X1)
    inside = cam.contains(uv, margin=1)
    u, v = np.rint(uv[inside]).astype(int).T
    back = rays.reshape(cam.height, cam.width, 3)[v, u] * d1[v, u][:, None]
    err = np.linalg.norm(back - X1[inside], axis=1)
    assert inside.mean() > 0.8
    assert np.median(err) < 0.01  # 1 cm at 2 m: rounding to the nearest pixel dominates
    assert 1.5 < np.median(d0) < 3.0  # the camera flies about 2 m above the floor


def test_circuit_closes_a_loop():
    poses = circuit_poses(SeafloorConfig(num_frames=300))
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    path = steps.sum()
    start_to_end = [np.linalg.norm(poses[j, :3, 3] - poses[0, :3, 3]) for j in range(250, 300)]
    assert path > 10 and min(start_to_end) < 0.1  # the path passes over its start again
    assert np.allclose(np.linalg.det(poses[:, :3, :3]), 1) and steps.max() < 2 * steps.mean()


def test_render_is_deterministic_per_seed_and_rejects_upward_views():
    cfg = SeafloorConfig(**TINY, seed=3)
    floor_a, floor_b = make_seafloor(cfg), make_seafloor(cfg)
    assert np.array_equal(floor_a.texture, floor_b.texture) and np.array_equal(floor_a.height, floor_b.height)
    other = make_seafloor(SeafloorConfig(**TINY, seed=4))
    assert not np.array_equal(floor_a.height, other.height)
    pose = circuit_poses(cfg)[0]
    rgb, rng = render(floor_a, pixel_rays(cfg.camera()), pose)
    X = pose[:3, 3] + rng[..., None] * (pixel_rays(cfg.camera()) @ pose[:3, :3].T)
    assert np.abs(X[..., 2] - floor_a.height_at(X[..., 0], X[..., 1])).max() < 0.01  # hits lie on the floor
    up = pose.copy()
    up[:3, :3] = pose[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    with pytest.raises(ValueError, match="downward"):
        render(floor_a, pixel_rays(cfg.camera()), up)


def test_unknown_level_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="jerlov_9C"):
        synthetic_sequence("muddy", cache_dir=tmp_path, progress=False, **TINY)


def test_turbid_level_loses_contrast(tmp_path):
    clear = synthetic_sequence("clear", cache_dir=tmp_path, progress=False, **TINY)
    murky = synthetic_sequence("jerlov_9C", cache_dir=tmp_path, progress=False, **TINY)
    again = synthetic_sequence("jerlov_9C", cache_dir=tmp_path, progress=False, **TINY)
    a, b = clear.load(4)[0].astype(float), murky.load(4)[0].astype(float)
    contrast = [np.mean([im[..., c].std() for c in range(3)]) for im in (a, b)]  # per channel: not the colour cast
    assert contrast[1] < 0.7 * contrast[0]
    assert np.array_equal(murky.load(4)[0], again.load(4)[0])
    assert np.allclose(murky.groundtruth.poses, clear.groundtruth.poses)
