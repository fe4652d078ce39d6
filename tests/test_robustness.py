"""The robustness-matrix generator: the path does what its knobs say, variants render, cache and read back."""

from __future__ import annotations

import numpy as np
import pytest

from ruslam.data.robustness import SurveyConfig, robustness_sequence, survey_poses

TINY = dict(width=64, height=48, straights=(3, 2), turn_deg=30.0, laps=1.2, progress=False)


def _yaw_steps(poses: np.ndarray) -> np.ndarray:
    """Change per frame (deg) of the direction of travel over the floor."""
    move = np.diff(poses[:, :2, 3], axis=0)
    return np.rad2deg(np.abs(np.diff(np.unwrap(np.arctan2(move[:, 1], move[:, 0])))))


@pytest.mark.parametrize("step, turn, pitch", [(0.15, 10.0, 0.0), (0.05, 2.5, 60.0), (0.1, 6.0, 30.0)])
def test_path_moves_turns_and_looks_as_asked(step, turn, pitch):
    cfg = SurveyConfig(step=step, turn_deg=turn, pitch_deg=pitch, altitude=3.0, straights=(10, 4), laps=1.15)
    poses = survey_poses(cfg)
    assert len(poses) == round(1.15 * (28 + 360 / turn))
    xy_steps = np.linalg.norm(np.diff(poses[:, :2, 3], axis=0), axis=1)
    assert np.allclose(xy_steps, step * 3.0, rtol=0.02)  # the chord of a corner is a hair shorter than the arc
    yaw = _yaw_steps(poses)
    assert yaw.max() == pytest.approx(turn, abs=0.05 * turn) and np.median(yaw[:8]) < 0.01  # straight start
    assert abs(yaw[:int(cfg.lap_frames)].sum() - 360) < 2 * turn  # a lap turns 360 degrees
    down = np.array([0.0, 0.0, -1.0])
    tilt = np.rad2deg(np.arccos(np.clip(poses[:, :3, 2] @ down, -1, 1)))
    assert np.allclose(tilt, pitch, atol=1e-6)  # the wobble rolls about the optical axis only
    assert np.allclose(np.linalg.det(poses[:, :3, :3]), 1)
    assert np.abs(poses[:, 2, 3] - 3.0).max() < 0.1 * 3.0  # altitude, with a gentle heave
    end = poses[int(cfg.lap_frames):, :2, 3]  # the second lap flies over the start again
    assert cfg.revisits and np.linalg.norm(end - poses[0, :2, 3], axis=1).min() < step * 3.0


def test_bad_knobs_are_refused_with_their_name(tmp_path):
    with pytest.raises(ValueError, match="unknown knob.*'tilt'"):
        robustness_sequence("x", cache_dir=tmp_path, tilt=3)
    with pytest.raises(ValueError, match="pitch_deg must be within 0-60"):
        SurveyConfig(pitch_deg=75)
    with pytest.raises(ValueError, match="Jerlov"):
        SurveyConfig(water="muddy")


def test_variant_renders_once_and_reads_back_with_its_ground_truth(tmp_path):
    seq = robustness_sequence("v", cache_dir=tmp_path, fps=20.0, water=None, **TINY)
    cfg = SurveyConfig(fps=20.0, water=None, **{k: v for k, v in TINY.items() if k != "progress"})
    assert len(seq) == cfg.num_frames and seq.name == "v" and not seq.stereo
    assert np.allclose(np.diff(seq.timestamps), 0.05)
    assert np.allclose(seq.groundtruth.poses, survey_poses(cfg), atol=1e-8)
    image = seq.load(0)[0]
    assert image.shape == (48, 64, 3) and image.std() > 10
    folder = seq.image_paths[0][0].parents[3]
    stamp = folder.stat().st_mtime_ns
    again = robustness_sequence("v", cache_dir=tmp_path, fps=20.0, water=None, **TINY)
    assert folder.stat().st_mtime_ns == stamp and np.array_equal(again.load(3)[0], seq.load(3)[0])
    assert len(list(tmp_path.iterdir())) == 1
    gaps = robustness_sequence("v", cache_dir=tmp_path, fps=20.0, water=None, dropped=[[2, 4], [6, 7]], **TINY)
    assert len(gaps) == len(seq) - 3 and len(list(tmp_path.iterdir())) == 1  # the same rendering, frames left out
    assert np.allclose(gaps.timestamps[:4], seq.timestamps[[0, 1, 4, 5]])
    assert np.allclose(gaps.groundtruth.poses, seq.groundtruth.poses)  # the ground truth stays whole
    with pytest.raises(ValueError, match="dropped frames"):
        robustness_sequence("v", cache_dir=tmp_path, fps=20.0, water=None, dropped=[[0, 10**4]], **TINY)


def test_lens_distortion_is_rendered_and_written_to_the_calibration(tmp_path):
    """k1: every pixel is rendered along the ray that the distorted camera's model assigns it (projecting the ray
    back lands on the pixel), and the calibration read back carries the coefficients the SLAM undistorts with."""
    from ruslam.data.synthetic_sequence import pixel_rays

    cfg = SurveyConfig(k1=-0.3, width=64, height=48)
    camera = cfg.camera()
    rays = pixel_rays(camera).reshape(-1, 3)
    u, v = np.meshgrid(np.arange(64), np.arange(48))
    np.testing.assert_allclose(camera.project(rays), np.stack([u.ravel(), v.ravel()], 1), atol=1e-3)
    corner = rays[0] / rays[0, 2]
    assert np.hypot(*corner[:2]) > 1.05 * np.hypot(-camera.cx / camera.fx, -camera.cy / camera.fy)  # barrel
    seq = robustness_sequence("lens", cache_dir=tmp_path, frames=2, k1=-0.3, **TINY)
    np.testing.assert_allclose(seq.cameras[0].dist, [-0.3, 0.15, 0, 0])
    assert SurveyConfig().key() != SurveyConfig(k1=-0.3).key()


def test_texture_and_water_knobs_change_the_pixels_the_right_way(tmp_path):
    def contrast(**knobs):
        seq = robustness_sequence("c", cache_dir=tmp_path, frames=2, **{**TINY, **knobs})
        grey = seq.load(1)[0].astype(np.float64).mean(axis=2)
        return grey[grey.shape[0] // 2:].std()  # the near half of the view (pitched cameras see far water above)

    full = contrast(water=None, noise_std=0.0)
    assert contrast(water=None, noise_std=0.0, contrast=0.3) < 0.5 * full
    assert contrast(water="9C", noise_std=0.0) < contrast(water="I", noise_std=0.0) < full


def test_stereo_variant_has_the_baseline(tmp_path):
    seq = robustness_sequence("s", cache_dir=tmp_path, frames=3, stereo=True, baseline=0.2, **TINY)
    left, right = seq.load(2)
    assert seq.stereo and np.allclose(seq.T_cam0_cam1[:3, 3], [0.2, 0, 0])
    assert left.shape == right.shape and not np.array_equal(left, right)


def test_pool_scene_casts_floor_walls_and_open_water_at_their_true_ranges():
    """A camera 0.3 m above the floor looking straight down sees the floor at its height; one looking level at a
    wall sees it at the wall's distance, open water above the wall's top edge, the floor below."""
    from ruslam.data.synthetic_sequence import downward_poses, pixel_rays
    from ruslam.data.tiled_pool import DEPTH_M, make_pool, render_pool

    pool = make_pool(np.array([[-1.0, -0.5], [1.0, 0.5]]), tile_m=0.05, seed=0)
    camera = SurveyConfig(width=64, height=48).camera()
    rays = pixel_rays(camera)
    at = np.array([[0.2, 0.1, 0.3]])
    down = downward_poses(at, np.array([[1.0, 0, 0]]), 0.0, np.zeros(1))[0]
    rgb, rng = render_pool(pool, rays, down)
    np.testing.assert_allclose(rng * rays[..., 2], 0.3, rtol=1e-5)  # depth along the axis: the height
    assert rgb.shape == (48, 64, 3) and rgb.std() > 0.05
    level = downward_poses(at + [0, 0, DEPTH_M - 0.6], np.array([[1.0, 0, 0]]), 90.0, np.zeros(1))[0]
    _, rng = render_pool(pool, rays, level)
    assert rng[24, 32] * rays[24, 32, 2] == pytest.approx(pool.half_x - 0.2, rel=1e-5)  # the +x wall, level ahead
    assert np.isinf(rng[0]).all() and np.isfinite(rng[-1]).all()  # above the wall's top / the floor near the wall


def test_pool_tiles_repeat_at_their_size_in_the_image():
    """Looking straight down from height h, grout lines repeat every f * tile / h pixels."""
    from ruslam.data.synthetic_sequence import downward_poses, pixel_rays
    from ruslam.data.tiled_pool import make_pool, render_pool

    cfg = SurveyConfig(width=256, height=192)
    camera = cfg.camera()
    pose = downward_poses(np.array([[0.0, 0.0, 0.5]]), np.array([[1.0, 0, 0]]), 0.0, np.zeros(1))[0]
    for tile in (0.04, 0.06):
        rgb, _ = render_pool(make_pool(np.zeros((1, 2)), tile_m=tile, seed=1), pixel_rays(camera), pose)
        profile = rgb.mean(axis=(0, 2)) - rgb.mean()  # grout columns are bright
        spectrum = np.abs(np.fft.rfft(profile))
        period = len(profile) / (2 + np.argmax(spectrum[2:]))  # the strongest frequency (the mean left out)
        assert period == pytest.approx(camera.fx * tile / 0.5, rel=0.08)


def test_pool_variant_renders_and_reads_back(tmp_path):
    seq = robustness_sequence("pool", cache_dir=tmp_path, frames=3, scene="pool", altitude=0.3, pitch_deg=65,
                              tile_m=0.04, **TINY)
    image = seq.load(2)[0]
    assert image.shape == (48, 64, 3) and image.std() > 5
    assert SurveyConfig().key() != SurveyConfig(scene="pool").key() != SurveyConfig(scene="pool", tile_m=0.04).key()
    with pytest.raises(ValueError, match="pitch_deg must be within 0-80"):
        SurveyConfig(scene="pool", pitch_deg=85)
    with pytest.raises(ValueError, match="scene must be"):
        SurveyConfig(scene="reef")
