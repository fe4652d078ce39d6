"""The SLAM on real pixels: real ORB and XFeat on small ray-cast seafloor sequences (not the exact-projection fake).

Rendered at 320x240 into a temporary cache: a quarter lap (40 frames, 0.1 m per frame at 2 m altitude), the same
with frames blacked out in the middle (tracking must come back and stay one trajectory), a full lap (loop
closure; with a long blackout, a new map that is merged into the first when the path comes back over it) and three
laps (loop closures must not raise the error).
Also the extractors with the evaluation's options on robustness variants: a fast turn in turbid water, low texture,
the tiled pool. All slow: each runs in well under a few minutes on 2 cores.
"""

from __future__ import annotations

import numpy as np
import pytest

from ruslam import load_extractor
from ruslam.data.readers import Sequence, Trajectory
from ruslam.data.synthetic_sequence import synthetic_sequence
from ruslam.eval.trajectory import evaluate_trajectory
from ruslam.slam import SLAMConfig, run

pytestmark = pytest.mark.slow

SMALL = dict(width=320, height=240, focal=225.0, texture_res=2048, height_res=650)
KEYPOINTS = {"orb": 1000, "xfeat": 2000}  # the evaluation's budgets (XFeat at 1000 initialised from 90 points)


class BlackedOut(Sequence):
    """A sequence whose frames in `black` load as black images (a lamp failure, a sediment cloud)."""

    black: frozenset = frozenset()

    def load(self, i):
        images = super().load(i)
        return [np.zeros_like(im) for im in images] if i in self.black else images


def blacked_out(seq: Sequence, black) -> BlackedOut:
    out = BlackedOut(name=seq.name, cameras=seq.cameras, timestamps=seq.timestamps, image_paths=seq.image_paths,
                     T_cam0_cam1=seq.T_cam0_cam1, groundtruth=seq.groundtruth)
    out.black = frozenset(black)
    return out


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("seafloor")


@pytest.fixture(scope="module")
def quarter(cache):
    return synthetic_sequence("clear", cache_dir=cache, progress=False, num_frames=40, laps=0.25, **SMALL)


@pytest.fixture(scope="module")
def lap(cache):
    return synthetic_sequence("clear", cache_dir=cache, progress=False, num_frames=140, laps=1.12, **SMALL)


def _ape_fraction(seq, result):
    gt = seq.groundtruth
    errors = evaluate_trajectory(Trajectory(result.timestamps, result.poses), gt, "sim3")
    first, last = result.frame_indices.min(), result.frame_indices.max()
    return errors.ape_rmse / Trajectory(gt.timestamps[first:last + 1], gt.poses[first:last + 1]).path_length()


def _run(seq, name):
    return run(seq, load_extractor(name, max_keypoints=KEYPOINTS[name]), SLAMConfig(progress=False))


@pytest.mark.parametrize("name", ["orb", "xfeat"])
def test_real_extractor_tracks_a_rendered_quarter_lap(quarter, name):
    result = _run(quarter, name)
    start = result.initialized_at
    assert start <= 10, f"{name} initialised only at frame {start}"
    assert np.sum(result.frame_indices >= start) >= 0.97 * (len(quarter) - start)
    assert result.num_maps == 1
    assert _ape_fraction(quarter, result) <= 0.01


@pytest.mark.parametrize("name", ["orb", "xfeat"])
def test_tracking_recovers_after_blacked_out_frames(quarter, name):
    """XFeat finds 0-1 descriptor matches between the keyframes on either side of the gap (0.9 m and ~25 deg of
    heading apart at 320x240), so neither relocalisation nor a merge links them: the two-view bridge from the last
    tracked frame does."""
    black = range(18, 26)  # 8 frames = 0.8 m: the first frame after it overlaps its predecessor by ~60 %
    seq = blacked_out(quarter, black)
    result = _run(seq, name)
    after = result.frame_indices[result.frame_indices >= 26]
    before = result.frame_indices[result.frame_indices < 18]
    assert len(before) >= 12 and len(after) >= 12, (len(before), len(after), result.map_frames)
    # one connected trajectory through the gap: relocalised, or a new map merged back into the first
    assert len(result) == sum(result.map_frames[:1])
    assert _ape_fraction(seq, result) <= 0.02


def test_full_lap_closes_the_loop(lap):
    result = _run(lap, "xfeat")
    assert len(result.loops) >= 1
    assert result.tracked_ratio >= 0.95
    assert _ape_fraction(lap, result) <= 0.01


def test_loop_closures_over_three_laps_lower_the_error(cache):
    """Three laps over the same seafloor: the loops XFeat closes (each accepted only when it lowers the predicted
    reprojection cost) leave the trajectory better than the same run without loop closing (measured 0.023 % of the
    path against 0.108 %), never worse."""
    seq = synthetic_sequence("clear", cache_dir=cache, progress=False, num_frames=375, laps=3.0, **SMALL)
    with_loops = _run(seq, "xfeat")
    cfg = SLAMConfig(progress=False)
    cfg.loop.enabled = False
    without = run(seq, load_extractor("xfeat", max_keypoints=KEYPOINTS["xfeat"]), cfg)
    assert len(with_loops.loops) >= 1 and with_loops.num_maps == 1 and with_loops.tracked_ratio >= 0.98
    assert _ape_fraction(seq, with_loops) <= _ape_fraction(seq, without)


def test_long_blackout_starts_a_new_map_that_merges_at_the_revisit(lap):
    """No overlap across the gap: mutual nearest neighbours between frames 39 and 62 (46, none passing the ratio
    test) fit a motion 85 deg off with 33 points; only 8 distinctive matches lie along its epipolar lines (15
    needed), so no bridge: a new map starts instead and merges at the revisit."""
    black = range(40, 62)  # 2.6 m: no overlap across the gap, so tracking cannot resume in the first map
    seq = blacked_out(lap, black)
    result = _run(seq, "xfeat")
    assert len(result.merges) >= 1
    assert result.num_maps == 1
    assert np.any(result.frame_indices < 40) and np.any(result.frame_indices > 100)
    # frames lost at the gap's far edge: 3 failed relocalisations, then the new map waits for parallax to initialise
    # (measured 118 of the 118 frames outside the gap, one torch thread)
    assert len(result) >= 0.85 * (len(lap) - len(black))
    # measured 0.14 % (one thread); 2-3 % with earlier tracking defaults; the false bridge, or a wrong merge or
    # scale bookkeeping, leaves the second part 12 % or more off
    assert _ape_fraction(seq, result) <= 0.04


def test_orb_keeps_tracking_over_a_washed_out_seafloor(cache):
    """Low-contrast, sparse texture (grey std ~4, sensor noise 2.5 grey levels) through a corner. Before the 1 px blur
    ahead of CLAHE and the PnP-first descriptor fallback, ORB never got past 2 poses here (seeds 3 and 4, measured);
    now seed 4 tracks every frame at 0.26 % of the path (seed 3: 90 % of the frames in 2 maps, 0.26 %)."""
    from ruslam.data.robustness import robustness_sequence
    from ruslam.slam.conditioning import ImageConditioning

    seq = robustness_sequence("lowtex", cache_dir=cache, progress=False, seed=4, contrast=0.4, density=0.3, frames=80)
    cfg = SLAMConfig(progress=False, conditioning=ImageConditioning("auto", blur_sigma=1.0))
    result = run(seq, load_extractor("orb", max_keypoints=KEYPOINTS["orb"]), cfg)
    assert result.initialized_at <= 5
    assert np.sum(result.frame_indices >= result.initialized_at) >= 0.97 * (len(seq) - result.initialized_at)
    assert result.num_maps == 1
    assert _ape_fraction(seq, result) <= 0.01


def _grid_setup(name: str):
    """The extractor and SLAM settings `python evaluate.py task=slam dataset=robustness` runs `name` with."""
    from conftest import compose

    from ruslam.eval.slam_report import slam_config_for, slam_extractors
    from ruslam.slam.system import as_config

    cfg = compose("evaluate", ["task=slam", "dataset=robustness", "slam.progress=false"])
    built, _ = slam_extractors([name], cfg)
    return built[name], as_config(slam_config_for(cfg, name))


def test_xfeat_keeps_tracking_through_a_fast_turn_in_turbid_water(cache):
    """DEV `hard_s5` (Jerlov 3C, 10 deg/frame corners, 15 % of the altitude per frame, pitch 48 deg), first 45 frames.
    With CLAHE on flat frames only and a 0.5 descriptor gate, XFeat lost the track in the first
    corner: 24 of the 45 frames in 2 maps (measured); the evaluation's options (CLAHE on every frame, gate 0.6) keep
    one map."""
    from ruslam.data.robustness import robustness_sequence

    seq = robustness_sequence("hard_s5", cache_dir=cache, progress=False, seed=5, step=0.15, turn_deg=10,
                              pitch_deg=48, water="3C", frames=45)
    result = run(seq, *_grid_setup("xfeat"))
    assert result.num_maps == 1 and len(result) >= 0.95 * len(seq)
    assert _ape_fraction(seq, result) <= 0.01


@pytest.mark.parametrize("name, knobs, starts", [
    ("lowtex_s4", dict(seed=4, contrast=0.38, density=0.28, frames=60), (0, 40)),
    ("lowtex", dict(seed=2, contrast=0.35, density=0.25, frames=90), (5, 75)),
])
def test_xfeat_keeps_its_scale_over_low_texture(cache, name, knobs, starts):
    """XFeat as the evaluation runs it, loop closing off: ten steps late in the run keep the scale of ten early ones.
    DEV `lowtex_s4`, first 60 frames: XFeat's dense keypoints on low texture come in near-duplicate pairs that share a
    descriptor; a window ratio test against them rejected most right matches, tracking fell back to PnP on half-wrong
    matches, and the scale collapsed or held depending on floating-point details (BLAS threads). With duplicates
    inside the noise radius ignored, the scale must hold for any thread count.
    TEST `lowtex`, first 90 frames: the motion model misses most frames, so the fallbacks pose them with the two-view
    terms. Over a near-flat floor the two views' motion has a twin (6 deg of rotation, the translation 90 deg off)
    that the floor's points fit as well. Optimised from PnP's pose, frames settled in it and the steps shrank: frames
    75-85 made 0.20x the steps of frames 5-15 (measured). Started from the two-view motion that the motion prior
    picked, the steps keep their scale."""
    from ruslam.data.robustness import SurveyConfig, robustness_sequence, survey_poses

    seq = robustness_sequence(name, cache_dir=cache, progress=False, **knobs)
    extractor, cfg = _grid_setup("xfeat")
    cfg.loop.enabled = False
    result = run(seq, extractor, cfg)
    assert result.num_maps == 1 and len(result) >= 0.95 * len(seq)
    truth = survey_poses(SurveyConfig(**knobs))[:, :3, 3]
    f, c = result.frame_indices, result.poses[:, :3, 3]
    scale = [np.linalg.norm(c[k + 10] - c[k]) / np.linalg.norm(truth[f[k + 10]] - truth[f[k]]) for k in starts]
    assert 0.8 <= scale[1] / scale[0] <= 1.25


def test_orb_keeps_its_scale_over_pool_tiles(cache):
    """TEST `pool` (a forward-looking camera 0.3 m above 4.5 cm tiles, 3 cm a frame), first 80 frames: every step
    could match a corner to its neighbour one tile off. ORB, as `evaluate.py` runs it, keeps one map at 0.21 % of the
    path (measured; 0.20-0.35 % on seeds 2, 5 and 6)."""
    from ruslam.data.robustness import robustness_sequence

    seq = robustness_sequence("pool", cache_dir=cache, progress=False, seed=2, scene="pool", altitude=0.3,
                              pitch_deg=64, tile_m=0.045, straights=(30, 12), frames=80)
    result = run(seq, *_grid_setup("orb"))
    assert result.num_maps == 1 and len(result) == len(seq)
    assert _ape_fraction(seq, result) <= 0.01


def test_xfeat_closes_the_pool_lap_that_its_scale_drifted_around(cache):
    """DEV `pool_s3` (3.5 cm tiles, 3 cm a frame): XFeat's steps shrink along the lap (tile corners matched one
    tile off as the forward motion scales them), and the loop at the revisit must undo it. Judged with the points
    dragged rigidly with their keyframes, every correction raised the reprojection cost and was refused (4.55 % of the
    path, measured); with the points re-estimated for each side's poses, the loop closes (0.53 %)."""
    from ruslam.data.robustness import robustness_sequence

    seq = robustness_sequence("pool_s3", cache_dir=cache, progress=False, seed=3, scene="pool", altitude=0.3,
                              pitch_deg=62, tile_m=0.035, straights=(28, 12))
    result = run(seq, *_grid_setup("xfeat"))
    assert result.num_maps == 1 and len(result) == len(seq) and result.loops
    assert _ape_fraction(seq, result) <= 0.02


def test_xfeat_keeps_most_of_its_scale_around_the_pool_lap_without_loops(cache):
    """TEST `pool`, loop closing off: triangulating a keypoint with a free look-alike one tile further along its
    epipolar line, where the right keypoint was already mapped, made points at the look-alike's depth, and XFeat's
    steps shrank 4x along the lap (measured: estimated over true step 0.33 on the first straight, 0.09 on the last).
    Matched only where they also beat the mapped keypoints on those lines: 0.36 and 0.16."""
    from ruslam.data.robustness import robustness_sequence

    seq = robustness_sequence("pool", cache_dir=cache, progress=False, seed=2, scene="pool", altitude=0.3,
                              pitch_deg=64, tile_m=0.045, straights=(30, 12))
    extractor, cfg = _grid_setup("xfeat")
    cfg.loop.enabled = False
    result = run(seq, extractor, cfg)
    assert result.num_maps == 1 and len(result) == len(seq)
    truth = seq.groundtruth.positions[np.searchsorted(seq.groundtruth.timestamps, seq.timestamps - 1e-6)]
    c = result.poses[:, :3, 3]
    step = [np.linalg.norm(c[k + 10] - c[k]) / np.linalg.norm(truth[k + 10] - truth[k]) for k in (17, 155)]
    assert step[1] / step[0] >= 0.35


def test_xfeat_closes_the_pool_lap_without_a_step_at_the_corrected_group(cache):
    """TEST `pool`: XFeat's revisit (frame 147 to frame 0) closes after its steps shrank 2.3x along the lap. Fusing
    the loop's points linked a keyframe just before the corrected group to it; taken as a loop link, measured on the
    corrected poses, it held that keyframe in place, and the correction left a 0.32 m step between two frames 3 cm
    apart (10.5x the true step; 1.80 % of the path, measured). Not a loop link: every step within 1.2x, 0.37 %."""
    from ruslam.data.robustness import robustness_sequence
    from ruslam.slam.geometry import umeyama

    seq = robustness_sequence("pool", cache_dir=cache, progress=False, seed=2, scene="pool", altitude=0.3,
                              pitch_deg=64, tile_m=0.045, straights=(30, 12))
    result = run(seq, *_grid_setup("xfeat"))
    assert result.num_maps == 1 and len(result) == len(seq) and result.loops
    truth = seq.groundtruth.positions[np.searchsorted(seq.groundtruth.timestamps, seq.timestamps - 1e-6)]
    S = umeyama(result.poses[:, :3, 3], truth)
    c = result.poses[:, :3, 3] @ S[:3, :3].T + S[:3, 3]
    step = np.linalg.norm(np.diff(c, axis=0), axis=1) / np.linalg.norm(np.diff(truth, axis=0), axis=1)
    assert step.max() < 3.0
    assert _ape_fraction(seq, result) <= 0.01


def test_uwnet_closes_no_loop_between_two_corners_of_the_tiled_pool(cache):
    """TEST `pool` from frame 2: at the lap's second corner (frame 61) UWNet's keyframe matches the floor of the first
    (frame 34), 0.75 m away and a whole number of tiles off. That loop lowered the predicted reprojection cost and
    closed before the revisit did (4.51 % of the path, measured). Its correction turns the camera back by the corner's
    90 deg and moves it back by nearly the path between them, which no drift does: refused, the revisit alone closes
    (0.28 %)."""
    from ruslam.data.robustness import robustness_sequence

    seq = robustness_sequence("pool", cache_dir=cache, progress=False, seed=2, scene="pool", altitude=0.3,
                              pitch_deg=64, tile_m=0.045, straights=(30, 12))
    seq = seq.subset(range(2, len(seq)))
    result = run(seq, *_grid_setup("uwnet_xfeat"))
    assert result.num_maps == 1 and len(result) == len(seq)
    truth = seq.groundtruth.positions[np.searchsorted(seq.groundtruth.timestamps, seq.timestamps - 1e-6)]
    assert all(np.linalg.norm(truth[a] - truth[b]) < 0.4 for a, b in result.loops)  # revisits, views overlapping
    assert _ape_fraction(seq, result) <= 0.03


def test_uwnet_closes_the_pool_revisit_that_its_drift_makes_the_cost_check_refuse(cache):
    """DEV `pool_s4`: after UWNet's drift around the lap, its revisit (frames 138-162 to frames 0-24) verified in 11
    consecutive keyframes, and each predicted correction raised the map's reprojection cost and was refused: no loop,
    5.01 % of the path (measured). Verified three times in a row, it closes (frame 142 to frame 8: 1.56 %)."""
    from ruslam.data.robustness import robustness_sequence

    seq = robustness_sequence("pool_s4", cache_dir=cache, progress=False, seed=4, scene="pool", altitude=0.3,
                              pitch_deg=66, tile_m=0.05, straights=(26, 12))
    result = run(seq, *_grid_setup("uwnet_xfeat"))
    assert result.num_maps == 1 and len(result) == len(seq) and result.loops
    truth = seq.groundtruth.positions[np.searchsorted(seq.groundtruth.timestamps, seq.timestamps - 1e-6)]
    assert all(np.linalg.norm(truth[a] - truth[b]) < 0.4 for a, b in result.loops)  # revisits, views overlapping
    assert _ape_fraction(seq, result) <= 0.03


def test_one_trajectory_across_dropped_frames_in_a_turn(lap):
    """Frames 20-27 dropped where the path turns: 1.3 m and 16 deg between two consecutive frames, beyond every
    search window. Tracking fails, relocalisation finds nothing (no revisit), and the two-view bridge from the last
    tracked frame keeps every frame in one map at the accuracy of the unbroken run; without the bridge the run
    splits into two maps."""
    seq = lap.subset([*range(20), *range(28, 50)])
    cfg = SLAMConfig(progress=False)
    cfg.loop.enabled = False
    result = run(seq, load_extractor("orb", max_keypoints=KEYPOINTS["orb"]), cfg)
    assert result.num_maps == 1 and len(result) == len(seq) and len(result.bridges) >= 1
    assert _ape_fraction(seq, result) <= 0.01
    cfg.tracking.bridge = False
    assert run(seq, load_extractor("orb", max_keypoints=KEYPOINTS["orb"]), cfg).num_maps > 1


def test_two_view_odometry_baseline_on_real_pixels(quarter):
    """The chained two-view baseline poses every frame of a quarter lap in one segment, well inside 5 % of the path
    (it has no map and no bundle adjustment: its scale drifts, so it is bounded, not compared with the SLAM)."""
    from ruslam.slam import two_view_odometry

    result = two_view_odometry.run(quarter, load_extractor("orb", max_keypoints=KEYPOINTS["orb"]),
                                   SLAMConfig(progress=False))
    assert result.num_maps == 1 and len(result) == len(quarter)
    assert _ape_fraction(quarter, result) <= 0.05


def test_two_view_odometry_poses_frames_that_wait_for_parallax(cache):
    """At four times the frame rate most frames move too little to fix a step: they wait on the last posed frame and
    are posed by interpolation, so every frame keeps a pose in one segment."""
    from ruslam.slam import two_view_odometry

    slow = synthetic_sequence("clear", cache_dir=cache, progress=False, num_frames=160, laps=0.25, **SMALL)
    result = two_view_odometry.run(slow, load_extractor("orb", max_keypoints=KEYPOINTS["orb"]),
                                   SLAMConfig(progress=False))
    assert result.num_maps == 1 and len(result) == len(slow)
    assert _ape_fraction(slow, result) <= 0.05
