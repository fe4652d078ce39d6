"""dataset=folder: every EuRoC / TUM / image-folder sequence under a root, mono or stereo, titled accordingly."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from conftest import compose

from ruslam.data.readers import Trajectory, read_tum_trajectory, write_tum_trajectory
from ruslam.data.robustness import robustness_sequence
from ruslam.data.sequence_folder import find_sequences, read_sequence

CALIBRATION = "model: pinhole\nwidth: 64\nheight: 48\nintrinsics: [45.0, 45.0, 31.5, 23.5]\ndistortion: []\n"


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    """A EuRoC stereo sequence, the same frames as a TUM RGB-D folder and as an image folder, plus clutter."""
    tmp = tmp_path_factory.mktemp("folder")
    seq = robustness_sequence("tiny", cache_dir=tmp / "cache", progress=False, frames=8, width=64, height=48,
                              stereo=True)
    root = tmp / "data"
    shutil.copytree(seq.image_paths[0][0].parents[3], root / "euroc" / "MH_tiny")
    gt = Trajectory(seq.groundtruth.timestamps, seq.groundtruth.poses)
    tum, folder = root / "tum" / "desk", root / "mine"
    for d in (tum / "rgb", folder):
        d.mkdir(parents=True)
    lines = []
    for i, paths in enumerate(seq.image_paths):
        shutil.copy(paths[0], tum / "rgb" / f"{seq.timestamps[i]:.6f}.png")
        shutil.copy(paths[0], folder / f"{seq.timestamps[i]:.6f}.png")
        lines.append(f"{seq.timestamps[i]:.6f} rgb/{seq.timestamps[i]:.6f}.png")
    (tum / "rgb.txt").write_text("# timestamp filename\n" + "\n".join(lines) + "\n")
    for d in (tum, folder):
        (d / "calibration.yaml").write_text(CALIBRATION)
        write_tum_trajectory(d / "groundtruth.txt", gt)
    (root / "notes").mkdir()
    (root / "notes" / "readme.txt").write_text("not a sequence")
    return root


def test_finds_each_format_and_reads_it(root):
    found = find_sequences(root)
    assert found == {"euroc/MH_tiny": "euroc/MH_tiny", "mine": "mine", "tum/desk": "tum/desk"}
    assert find_sequences(root / "tum" / "desk") == {"desk": "."}  # the root may be one sequence
    mono = {name: read_sequence(root / rel) for name, rel in found.items()}
    assert all(len(s) == 8 and not s.stereo and s.groundtruth is not None for s in mono.values())
    assert np.allclose(mono["mine"].groundtruth.poses, mono["euroc/MH_tiny"].groundtruth.poses, atol=1e-6)
    assert read_sequence(root / "euroc" / "MH_tiny", sensor="stereo").stereo
    assert not read_sequence(root / "tum" / "desk", sensor="stereo").stereo  # one camera: mono, with a warning
    with pytest.raises(FileNotFoundError, match="No sequence found"):
        find_sequences(root / "notes")
    with pytest.raises(FileNotFoundError, match="is not a sequence"):
        read_sequence(root / "notes")


def _fake(sequence, extractor, cfg):
    """The ground truth at half scale, or nothing for the TUM folder (a run that never initialised)."""
    from test_slam_report import FakeEstimate

    gt, n = sequence.groundtruth, len(sequence)
    if sequence.name == "tum/desk":
        return FakeEstimate(np.zeros(0), np.zeros((0, 4, 4)), n, np.full(n, 0.01))
    poses = gt.poses.copy()
    poses[:, :3, 3] *= 0.5
    return FakeEstimate(gt.timestamps, poses, n, np.full(n, 0.01))


@pytest.mark.parametrize("sensor", ["mono", "stereo"])
def test_evaluate_runs_every_sequence_with_a_title_that_says_what_it_is(root, tmp_path, sensor, capsys):
    from ruslam.config_checks import check_evaluate
    from ruslam.eval.slam_report import run

    cfg = compose("evaluate", ["task=slam", "dataset=folder", f"dataset.root={root}", f"dataset.sensor={sensor}",
                               f"out_dir={tmp_path}", "extractors=[orb]", "task.two_view_vo=[]"])
    check_evaluate(cfg)  # the entry point's early check accepts a folder whose sequences are still to be found
    out = run(cfg, slam_run=_fake)
    by_seq = {r["sequence"]: r for r in out["results"]}
    assert set(by_seq) == {"euroc/MH_tiny", "mine", "tum/desk"}
    assert by_seq["mine"]["ok"] and by_seq["mine"]["ape"] < 1e-6  # Sim3 undoes the half scale
    assert by_seq["euroc/MH_tiny"]["ok"] == (sensor == "mono")  # SE3 (stereo) keeps it: diverged from the box
    title = "data, 3 sequence(s) (" + ("monocular" if sensor == "mono" else "mono and stereo") + ")"
    assert title in out["table"] and "EuRoC" not in out["table"]
    assert not by_seq["tum/desk"]["ok"] and not (tmp_path / "trajectories" / "tum/desk").exists()
    assert "tum/desk / orb: no frame got a pose, so no trajectory file is written" in capsys.readouterr().out
    written = read_tum_trajectory(tmp_path / "trajectories" / "mine" / "orb.txt")
    assert len(written) == 8


def test_a_list_of_names_and_a_missing_root(root, tmp_path):
    from ruslam.eval.slam_report import run

    cfg = compose("evaluate", ["task=slam", "dataset=folder", f"dataset.root={root}", f"out_dir={tmp_path}",
                               "extractors=[orb]", "dataset.sequences=[mine]", "task.two_view_vo=[]"])
    assert [r["sequence"] for r in run(cfg, slam_run=_fake)["results"]] == ["mine"]
    with pytest.raises(ValueError, match=r"needs dataset.root"):
        run(compose("evaluate", ["task=slam", "dataset=folder", f"out_dir={tmp_path}"]), slam_run=_fake)
    with pytest.raises(ValueError, match="no pose"):
        write_tum_trajectory(tmp_path / "empty.txt", Trajectory(np.zeros(0), np.zeros((0, 4, 4))))
    assert not (tmp_path / "empty.txt").exists()


def test_every_n_th_frame_a_lower_frame_rate(root, tmp_path):
    from ruslam.eval.slam_report import run

    for rel in ("mine", "tum/desk", "euroc/MH_tiny"):
        full, third = read_sequence(root / rel, sensor="stereo"), read_sequence(root / rel, sensor="stereo", every=3)
        assert np.array_equal(third.timestamps, full.timestamps[[0, 3, 6]])
        assert third.image_paths == [full.image_paths[i] for i in (0, 3, 6)]  # both cameras of a stereo frame
        assert len(third.groundtruth) == len(full.groundtruth)  # evaluated on the whole ground truth
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="every must be a positive integer"):
            read_sequence(root / "mine", every=bad)
    cfg = compose("evaluate", ["task=slam", "dataset=folder", f"dataset.root={root}", f"out_dir={tmp_path}",
                               "extractors=[orb]", "dataset.sequences=[mine]", "dataset.every=3",
                               "task.two_view_vo=[]"])
    given = []
    out = run(cfg, slam_run=lambda sequence, *args: given.append(len(sequence)) or _fake(sequence, *args))
    assert given == [3] and "data, 1 sequence(s) (monocular, 1 frame in 3)" in out["table"]
