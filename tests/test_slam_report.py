"""task=slam: the failure rule, the Avg-over-common-successes rule and the report files."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import compose

from ruslam.eval.slam_report import (
    RunResult,
    average_over_common_successes,
    failure_reason,
    results_table,
)

RULE = SimpleNamespace(min_tracked=0.8, bound_margin_m=1.0)


def test_failure_rule():
    ref = np.array([[0, 0, 0], [4, 0, 0], [4, 3, 1.0]])
    assert failure_reason(1.0, ref + 0.1, ref, RULE) == ""
    assert "tracked 50%" in failure_reason(0.5, ref, ref, RULE)
    far = ref.copy()
    far[1, 0] = 6.5  # 2.5 m beyond x_max = 4, margin 1 m
    assert "diverged: 1.50 m" in failure_reason(1.0, far, ref, RULE)
    assert failure_reason(1.0, far, ref, SimpleNamespace(min_tracked=0.8, bound_margin_m=None)) == ""
    assert failure_reason(0.9, None, ref, RULE) == "no pose matched the ground truth"
    # path 4 + sqrt(10) = 7.16 m: 10 % of it is 0.716 m
    ape_rule = SimpleNamespace(min_tracked=0.8, bound_margin_m=None, max_ape_fraction=0.1)
    assert failure_reason(1.0, ref, ref, ape_rule, ape=0.70) == ""
    assert "diverged: APE 0.80 m > 10% of the 7.16 m path" in failure_reason(1.0, ref, ref, ape_rule, ape=0.80)


def _results():
    ok = lambda s, m, ape, rpe: RunResult(s, m, True, "", ape=ape, rpe=rpe, tracked=1.0)  # noqa: E731
    return [ok("01", "orb", 0.10, 0.02), ok("01", "uwnet", 0.05, 0.01),
            RunResult("02", "orb", False, "tracked 10%", tracked=0.1), ok("02", "uwnet", 0.40, 0.30),
            ok("03", "orb", 0.30, 0.04), ok("03", "uwnet", 0.20, 0.03)]


def test_top_view_is_the_plane_the_ground_truth_spreads_in():
    from ruslam.eval.slam_report import top_view_axes

    t = np.linspace(0, 1, 20)
    floor = np.c_[np.sin(3 * t), 0.01 * t, 2 * t]  # a crawler on a floor, y down: x-z
    aerial = np.c_[2 * t, np.cos(3 * t), 0.02 * t]  # a survey at constant altitude: x-y
    assert top_view_axes(floor) == (0, 2)
    assert top_view_axes(aerial) == (0, 1)


def test_avg_is_over_sequences_where_every_method_succeeds():
    avg, common = average_over_common_successes(_results(), ["01", "02", "03"], ["orb", "uwnet"], ["ape", "rpe"])
    assert common == ["01", "03"]
    assert avg[("orb", "ape")] == pytest.approx(0.20) and avg[("uwnet", "ape")] == pytest.approx(0.125)
    assert avg[("uwnet", "rpe")] == pytest.approx(0.02)  # 02's 0.30 is left out although uwnet succeeded there
    none_common, common = average_over_common_successes(_results()[2:4], ["02"], ["orb", "uwnet"], ["ape"])
    assert common == [] and math.isnan(none_common[("uwnet", "ape")])


def test_table_layout_marks_failures_and_best():
    md, table = results_table(_results(), ["01", "02", "03"], ["orb", "uwnet"], ["ape", "rpe"],
                              {"orb": "ORB", "uwnet": "UWNet"}, "AQUALOC")
    lines = md.splitlines()
    assert "| Sequence | ORB APE | ORB RPE | UWNet APE | UWNet RPE |" in lines
    assert "| 02 | × | × | 0.400 | 0.300 |" in lines
    assert "| 01 | 0.100 | 0.020 | **0.050** | **0.010** |" in lines
    assert "| Avg | 0.200 | 0.030 | **0.125** | **0.020** |" in lines
    rows = table.splitlines()
    assert rows[0] == "Sequence,orb_ape,orb_rpe,uwnet_ape,uwnet_rpe" and rows[2] == "02,x,x,0.4,0.3"
    sweep, _ = results_table(_results(), ["02"], ["orb", "uwnet"], ["ape", "tracked"], {}, "sweep")
    assert "| 02 | × | 10% | 0.400 | **100%** |" in sweep.splitlines()  # a failed run still shows how far it got
    md3, _ = results_table(_results(), ["01", "02", "03"], ["orb", "uwnet"], ["ape"], {}, "EuRoC")
    assert "| Sequence | orb | uwnet |" in md3.splitlines()  # Table 3: one APE column per method


@dataclass
class FakeEstimate:
    timestamps: np.ndarray
    poses: np.ndarray
    num_frames: int
    timings: np.ndarray
    num_keyframes: int = 3
    loops: list = field(default_factory=list)


def fake_slam(sequence, extractor, cfg):
    """Ground truth seen through a scale of 0.5 plus 1 cm noise (ORB) or tracking lost after 30% (others)."""
    gt = sequence.groundtruth
    n = len(sequence)
    poses = gt.poses.copy()
    poses[:, :3, 3] = 0.5 * poses[:, :3, 3] + 0.005 * np.random.default_rng(0).standard_normal((n, 3))
    keep = n if type(extractor).__name__ == "ORB" else int(0.3 * n)
    return FakeEstimate(gt.timestamps[:keep], poses[:keep], n, np.full(n, 0.01))


def _tiny_cfg(tmp_path, extractors):
    return compose("evaluate", ["task=slam", f"out_dir={tmp_path}", f"extractors={extractors}",
                               "dataset.sequences=[clear]", f"dataset.reader.cache_dir={tmp_path / 'cache'}",
                               "dataset.reader.num_frames=10", "+dataset.reader.width=160",
                               "+dataset.reader.height=120", "+dataset.reader.focal=112.5",
                               "+dataset.reader.texture_res=512", "+dataset.reader.height_res=300",
                               "+dataset.reader.progress=false"])


def test_run_writes_tables_plots_and_sweep(tmp_path):
    cfg = _tiny_cfg(tmp_path, "[orb,sift,uwnet]")
    from ruslam.eval.slam_report import run

    out = run(cfg, slam_run=fake_slam)
    by_method = {r["method"]: r for r in out["results"]}
    assert by_method["orb"]["ok"] and 0 < by_method["orb"]["ape"] < 0.03  # Sim3 undid the 0.5 scale
    assert by_method["orb"]["fps"] == pytest.approx(100.0)
    assert not by_method["sift"]["ok"] and "tracked 30%" in by_method["sift"]["reason"]
    assert "uwnet" in out["skipped"]
    for name in ["table.md", "table.csv", "runs.md", "runs.csv", "results.json", "plots/clear.png", "sweep.png",
                 "trajectories/clear/orb.txt"]:
        assert (tmp_path / name).is_file(), name
    assert "| clear |" in (tmp_path / "table.md").read_text() and "×" in (tmp_path / "table.md").read_text()


def test_a_crashing_run_is_a_failed_cell(tmp_path):
    from ruslam.eval.slam_report import run

    def crash(sequence, extractor, cfg):
        raise RuntimeError("boom")

    out = run(_tiny_cfg(tmp_path, "[orb]"), slam_run=crash)
    assert out["results"][0]["reason"] == "crashed: RuntimeError: boom" and (tmp_path / "table.md").is_file()


def test_missing_dataset_names_what_to_download(tmp_path):
    cfg = compose("evaluate", ["task=slam", "dataset=euroc", f"out_dir={tmp_path}", f"dataset.root={tmp_path}"])
    from ruslam.eval.slam_report import run

    with pytest.raises(FileNotFoundError, match=r"EuRoC.*MH_01_easy.*asl.ethz.ch"):
        run(cfg, slam_run=fake_slam)


def test_euroc_layout_is_table3_with_se3_alignment(tmp_path):
    """A tiny stereo sequence in the EuRoC layout under dataset.root: one APE column per method, SE3 (no scale)."""
    from ruslam.data.synthetic_sequence import synthetic_sequence
    from ruslam.eval.slam_report import run

    seq = synthetic_sequence("clear", stereo=True, cache_dir=tmp_path / "cache", num_frames=10, width=160,
                             height=120, focal=112.5, texture_res=512, height_res=300, progress=False)
    root = tmp_path / "euroc"
    root.mkdir()
    (root / "MH_01_easy").symlink_to(seq.image_paths[0][0].parents[3])
    cfg = compose("evaluate", ["task=slam", "dataset=euroc", f"dataset.root={root}", f"out_dir={tmp_path / 'out'}",
                               "extractors=[orb]", "dataset.select=[MH01]"])
    out = run(cfg, slam_run=fake_slam)
    result = out["results"][0]
    assert result["ok"] and result["ape"] > 0.5  # the fake's 0.5 scale survives SE3 alignment
    assert "| Sequence | ORB |" in out["table"] and "| MH01 |" in out["table"] and "MH02" not in out["table"]
    with pytest.raises(ValueError, match="unknown sequence"):
        run(compose("evaluate", ["task=slam", "dataset=euroc", f"dataset.root={root}", "dataset.select=[MH9]",
                                 f"out_dir={tmp_path / 'out'}"]),
            slam_run=fake_slam)


def test_dataset_bound_and_per_name_extractor_options(tmp_path):
    """The synthetic dataset's 0.5 m bound fails a run that strays 2 m; ORB gets the SLAM's keypoint cap."""
    from ruslam.eval.slam_report import run

    seen = {}

    def strays(sequence, extractor, cfg):
        seen[type(extractor).__name__] = extractor.conf["max_keypoints"]
        est = fake_slam(sequence, extractor, cfg)
        est.poses = est.poses.copy()
        est.poses[len(est.poses) // 2, :3, 3] += 2.0  # one pose 2 m off, in the estimate's (half) scale
        return est

    out = run(_tiny_cfg(tmp_path, "[orb]"), slam_run=strays)
    assert not out["results"][0]["ok"] and "beyond the ground-truth box + 0.5 m" in out["results"][0]["reason"]
    assert seen == {"ORB": 1000}
    cfg = _tiny_cfg(tmp_path, "[orb]")
    cfg.dataset.failure.bound_margin_m = 5.0
    cfg.task.extractor_options = {"orb": {"max_keypoints": 500}}
    assert run(cfg, slam_run=strays)["results"][0]["ok"] and seen == {"ORB": 500}
    cfg.dataset.extractor_options = {"orb": {"max_keypoints": 300}}  # a dataset's own (e.g. its resolution's)
    run(cfg, slam_run=strays)
    assert seen == {"ORB": 300}


def test_robustness_matrix_reports_tracking_after_init_maps_and_ape_share(tmp_path):
    """dataset=robustness: variants given as knobs; a run that starts late but then keeps every frame scores 100 %
    after initialisation, the map count comes from the SLAM, APE is also given as a share of the path flown."""
    from ruslam.eval.slam_report import run

    def late_start(sequence, extractor, cfg):
        est = fake_slam(sequence, extractor, cfg)
        keep = slice(len(sequence) // 8, None)
        est.timestamps, est.poses = sequence.groundtruth.timestamps[keep], est.poses[keep]
        est.num_maps = 2
        est.map_frames = [len(est.timestamps), 2]  # a second map that never merged holds 2 frames
        return est

    cfg = compose("evaluate", ["task=slam", "dataset=robustness", "dataset.split=dev", f"out_dir={tmp_path}",
                               "extractors=[orb]", "dataset.select=[turn9]", f"dataset.reader.cache_dir={tmp_path}",
                               "dataset.reader.width=48", "dataset.reader.height=36",
                               "+dataset.splits.dev.turn9.frames=16", "task.two_view_vo=[]"])
    assert cfg.slam.max_frames is None  # the dataset runs every frame (the embedded sweep's cap is its own)
    result = run(cfg, slam_run=late_start)["results"][0]
    assert result["ok"] and result["frames"] == 16 and result["tracked"] == pytest.approx(14 / 16)
    assert result["tracked_after_init"] == pytest.approx(1.0) and result["maps"] == 2
    assert result["tracked_all_maps"] == pytest.approx(16 / 16)
    path = result["ape"] / result["ape_path"]  # the path over the 16 frames: 15 steps of 0.1 x 2 m
    assert path == pytest.approx(15 * 0.2, rel=0.02)
    table = (tmp_path / "table.md").read_text()
    assert "Robustness matrix, dev split" in table and "| turn9 | 88% | 100% | 2 |" in table


def test_failure_rule_uses_the_path_of_the_frames_run(tmp_path):
    """With slam.max_frames the APE bound is a share of the path actually flown, not of the whole sequence."""
    from ruslam.eval.slam_report import run

    def offset(sequence, extractor, cfg):  # 10 of the 16 frames, each pose 0.2 m off sideways, alternately
        n = 10
        poses = sequence.groundtruth.poses[:n].copy()
        poses[:, 1, 3] += 0.2 * (-1) ** np.arange(n)
        return FakeEstimate(sequence.groundtruth.timestamps[:n], poses, n, np.full(n, 0.01))

    overrides = ["task=slam", "dataset=robustness", "dataset.split=dev", f"out_dir={tmp_path}", "extractors=[orb]",
                 "dataset.select=[turn9]", f"dataset.reader.cache_dir={tmp_path}", "dataset.reader.width=48",
                 "dataset.reader.height=36", "+dataset.splits.dev.turn9.frames=16", "slam.max_frames=10"]
    result = run(compose("evaluate", overrides), slam_run=offset)["results"][0]
    assert not result["ok"] and "of the 1.80 m path" in result["reason"]  # 9 steps of 0.2 m, not 15


def test_evaluation_runs_each_extractor_with_the_python_presets(tmp_path):
    """`evaluate.py task=slam` and `preset(name)` give the same extractor options and SLAM settings, so the README's
    snippet reproduces the reported figures (the synchronous SLAM is seeded: same inputs, same trajectory)."""
    from ruslam.eval.slam_report import run
    from ruslam.slam import preset
    from ruslam.slam.system import as_config

    seen = {}

    def record(sequence, extractor, cfg):
        seen[type(extractor).__name__] = (extractor, as_config(cfg))
        return fake_slam(sequence, extractor, cfg)

    run(_tiny_cfg(tmp_path, "[orb,xfeat,uwnet_xfeat]"), slam_run=record)
    for name, kind in (("orb", "ORB"), ("xfeat", "XFeat"), ("uwnet_xfeat", "UWNetExtractor")):
        extractor, cfg = preset(name)
        evaluated, evaluated_cfg = seen[kind]
        assert type(extractor).__name__ == kind and extractor.conf == evaluated.conf
        for part in ("conditioning", "tracking", "mapping", "loop"):
            assert getattr(cfg, part) == getattr(evaluated_cfg, part), (name, part)
        assert type(cfg.pair_matcher) is type(evaluated_cfg.pair_matcher)
    assert seen["XFeat"][0].conf["resize_min"] == 640 and seen["XFeat"][1].tracking.min_inliers == 25
    assert seen["ORB"][1].conditioning.method == "auto" and seen["ORB"][1].pair_matcher is None
