"""TUM fr3 cabinet keyframes (real, weakly textured; optional real samples): runnable through dataset=folder, and
ORB-SLAM's ORB gives every frame enough keypoints to be used, where plain ORB leaves frames below the minimum."""

from __future__ import annotations

import numpy as np
import pytest

from ruslam.data.sequence_folder import find_sequences, read_sequence
from ruslam.models.classical import ORB
from ruslam.slam.tracking import TrackingConfig


@pytest.fixture
def cabinet(shared_data):
    root = shared_data / "sequences" / "tum_freiburg3_cabinet_keyframes"
    if not root.is_dir():
        pytest.skip(f"{root} is absent")
    return root


def test_cabinet_is_found_and_read_as_a_tum_sequence(cabinet):
    found = find_sequences(cabinet)
    assert found == {"tum_freiburg3_cabinet_keyframes": "."}
    seq = read_sequence(cabinet / found["tum_freiburg3_cabinet_keyframes"])
    assert len(seq) == 58 and not seq.stereo and seq.cameras[0].fx == pytest.approx(535.4)
    assert seq.groundtruth is not None and 8.0 < seq.groundtruth.path_length() < 8.6  # the 8.3 m circle
    assert np.allclose(seq.groundtruth.timestamps, seq.timestamps)


def test_orbslam_orb_leaves_no_frame_unusable(cabinet):
    seq = read_sequence(cabinet)
    minimum = TrackingConfig().min_keypoints
    ours, plain = ORB(max_keypoints=1000), ORB(max_keypoints=1000, distribution="opencv")
    counts = np.array([[len(e.extract(seq.load(i)[0])["keypoints"]) for e in (ours, plain)] for i in range(len(seq))])
    assert counts[:, 0].min() >= minimum and np.median(counts[:, 0]) > 1.5 * np.median(counts[:, 1])
    assert (counts[:, 1] < minimum).sum() >= 5  # plain ORB: the frames the issue saw skipped (9 measured)


@pytest.mark.slow
@pytest.mark.parametrize("name, max_ape_share", [("xfeat", 0.08), ("uwnet_xfeat", 0.06)])
def test_learned_extractors_track_the_whole_cabinet_in_one_map(cabinet, name, max_ape_share):
    """The SLAM as `python evaluate.py task=slam` runs it: LighterGlue (the evaluation's pair matcher) gives
    initialisation and the descriptor fallbacks the matches that nearest neighbours lack on this weakly textured,
    wide-baseline sequence (XFeat with kNN alone: 7 % of the frames in 3 maps), the essential matrix initialises
    from the first two keyframes (F: XFeat from frame 4, UWNet 66 % in 2 maps), and the two-view matches to the
    last frame hold each fallback pose's turn (without them XFeat took the orbit's turn for sideways travel:
    10.4-10.8 % from keyframes 0, 1 and 3)."""
    from conftest import compose

    from ruslam.data.readers import Trajectory
    from ruslam.eval.slam_report import slam_config_for, slam_extractors
    from ruslam.eval.trajectory import evaluate_trajectory
    from ruslam.slam.system import as_config, run

    cfg = compose("evaluate", ["task=slam", "slam.progress=false"])
    built, _ = slam_extractors([name], cfg)
    seq = read_sequence(cabinet)
    result = run(seq, built[name], as_config(slam_config_for(cfg, name)))
    assert result.num_maps == 1 and result.tracked_ratio >= 0.95
    ape = evaluate_trajectory(Trajectory(result.timestamps, result.poses), seq.groundtruth, "sim3").ape_rmse
    # measured XFeat 5.38 % (2.83-5.24 % from keyframes 1-3), UWNet 4.13 %; 6 % is the bound the project holds UWNet to
    assert ape <= max_ape_share * seq.groundtruth.path_length()
