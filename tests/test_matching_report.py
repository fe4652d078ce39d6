import csv
import json

import cv2
import numpy as np
import pytest
from conftest import compose

from ruslam.eval.matching_report import run

SMALL = ["dataset.size=[96,128]", "dataset.eval_size=[96,128]", "dataset.num_warps=2"]


def write_images(folder, n):
    folder.mkdir(parents=True)
    rng = np.random.default_rng(3)
    for i in range(n):
        small = (rng.random((12, 16, 3)) * 255).astype(np.uint8)
        cv2.imwrite(str(folder / f"img{i}.jpg"), cv2.resize(small, (128, 96), interpolation=cv2.INTER_NEAREST))
    return folder


def check_outputs(out, report, names):
    table = (out / "table.md").read_text()
    for label in names:
        assert f"| {label} |" in table
    assert "0-30°" in table and "30-90°" in table and "90-180°" in table
    rows = list(csv.DictReader((out / "table.csv").open()))
    assert {r["part"] for r in rows} >= {"overall", "0-30°", "30-90°", "90-180°"}
    png = cv2.imread(str(out / "mma_vs_threshold.png"))
    assert png is not None and png.shape[0] > 100
    assert report["pictures"] and all((out / p).is_file() for p in report["pictures"])
    assert json.loads((out / "results.json").read_text())["pairs"] == report["pairs"]
    assert not list(out.rglob("*.tmp*"))


def test_folder_run_writes_table_plot_pictures_and_skip_notes(tmp_path):
    src = write_images(tmp_path / "src", 3)
    cfg = compose("evaluate", ["task=matching", "dataset=upatches", f"dataset.root={src}", "dataset.num_images=3",
                               "extractors=[sift,orb,uwnet_no_am_dcn]", f"out_dir={tmp_path / 'out'}", *SMALL])
    report = run(cfg)
    out = tmp_path / "out"
    check_outputs(out, report, ["SIFT", "ORB"])
    assert report["pairs"] == 6 and set(report["results"]) == {"sift", "orb"}
    assert "no weights file configured" in report["skipped"]["uwnet_no_am_dcn"]
    assert "UWNet w/o AM-DCN (`uwnet_no_am_dcn`): no weights file configured" in (out / "table.md").read_text()
    for res in report["results"].values():
        bins = [res[b]["pairs"] for b in ("0-30°", "30-90°", "90-180°")]
        assert sum(bins) == 6  # every pair lands in exactly one rotation bin
        o = res["overall"]
        assert 0 <= o["rep"] <= 100 and 0 <= o["ms"] <= 100 and o["mma"] == pytest.approx(o["mma_curve"][2])
        assert np.all(np.diff(o["mma_curve"]) >= 0)  # MMA can only grow with the threshold
    # the header states the median zoom of the pairs (around 1 with the default builder)
    zooms = report["zooms"]
    assert len(zooms) == 6 and 0.7 < np.median(zooms) < 1.3
    assert f"median zoom {np.median(zooms):.2f}x" in (out / "table.md").read_text().splitlines()[0]


def test_unknown_extractor_is_one_sentence_before_any_work(tmp_path):
    src = write_images(tmp_path / "src", 1)
    cfg = compose("evaluate", ["task=matching", "dataset=upatches", f"dataset.root={src}", "dataset.num_images=1",
                               "extractors=[orb,surf]", f"out_dir={tmp_path / 'out'}", *SMALL])
    with pytest.raises(ValueError, match=r"^Unknown extractor 'surf' in extractors; expected one of \["):
        run(cfg)
    assert list((tmp_path / "out").iterdir()) == []


def test_folder_with_fewer_images_than_asked(tmp_path):
    src = write_images(tmp_path / "src", 2)
    cfg = compose("evaluate", ["task=matching", "dataset=upatches", f"dataset.root={src}", "dataset.num_images=30",
                               "extractors=[orb]", f"out_dir={tmp_path / 'out'}"])
    with pytest.raises(ValueError, match=r"holds 2 image\(s\) .*fewer than the 30 asked"):
        run(cfg)


def test_embedded_default_runs_tiny(tmp_path):
    # the default dataset (procedural scenes made pseudo-underwater) at a tiny size, default extractor list:
    # the ones not available here are skipped with a note, never an error
    cfg = compose("evaluate", ["task=matching", "dataset.num_images=2", "dataset.render_size=[96,128]",
                               f"out_dir={tmp_path}", *SMALL])
    report = run(cfg)
    assert report["pairs"] == 4 and {"sift", "orb"} <= set(report["results"])
    assert set(report["results"]) | set(report["skipped"]) == set(cfg.extractors)
    check_outputs(tmp_path, report, ["SIFT", "ORB"])
    manifest = json.loads((tmp_path / "upatches" / "upatches.json").read_text())
    assert manifest["source"] == "procedural" and "PseudoUnderwater" in manifest["degrade"]["_target_"]
    # the images are the degraded ones: a second build without degradation differs
    from ruslam.data.upatches import procedural_upatches

    clean = procedural_upatches(tmp_path / "clean", num_images=1, render_size=(48, 64), size=(96, 128),
                                eval_size=(96, 128), num_warps=1, degrade=None)
    degraded = cv2.imread(str(tmp_path / "upatches" / "v_000" / "1.ppm"))
    assert not np.array_equal(cv2.cvtColor(clean[0]["image1"], cv2.COLOR_RGB2BGR), degraded)


def test_hpatches_config_reads_the_official_layout(tmp_path):
    # one i_ and one v_ sequence of 3 images each at another size than the evaluation size; image k is image 1
    # shifted by a known translation, so a correct pipeline (H direction, resize update) matches SIFT almost
    # perfectly, and a wrong one cannot
    rng = np.random.default_rng(0)
    base = cv2.resize((rng.random((30, 40, 3)) * 255).astype(np.uint8), (200, 150), interpolation=cv2.INTER_CUBIC)
    for seq in ("i_one", "v_two"):
        folder = tmp_path / "hp" / seq
        folder.mkdir(parents=True)
        cv2.imwrite(str(folder / "1.ppm"), base)
        for k, shift in ((2, (7.0, -4.0)), (3, (-12.0, 9.0))):
            H = np.array([[1, 0, shift[0]], [0, 1, shift[1]], [0, 0, 1]])
            warped = cv2.warpPerspective(base, H, (200, 150), borderMode=cv2.BORDER_REFLECT)
            cv2.imwrite(str(folder / f"{k}.ppm"), warped)
            np.savetxt(folder / f"H_1_{k}", H)
    cfg = compose("evaluate", ["task=matching", "dataset=hpatches", f"dataset.root={tmp_path / 'hp'}",
                               "dataset.size=[120,160]", "extractors=[sift]", f"out_dir={tmp_path / 'out'}"])
    report = run(cfg)
    assert report["pairs"] == 4 and report["results"]["sift"]["0-30°"]["pairs"] == 4
    assert report["results"]["sift"]["overall"]["mma"] > 90


def test_weights_file_extractor_is_evaluated(tmp_path):
    # task.weights.<name> = a UWNet weights file -> that network is evaluated under its label (untrained here:
    # only the plumbing is checked, not its accuracy)
    import torch

    from ruslam.models.export import export_weights
    from ruslam.models.uwnet import UWNet

    torch.manual_seed(0)
    weights = export_weights(UWNet(attention=False, deformable=False), tmp_path / "no_am_dcn.pt")
    src = write_images(tmp_path / "src", 1)
    cfg = compose("evaluate", ["task=matching", "dataset=upatches", f"dataset.root={src}", "dataset.num_images=1",
                               "extractors=[uwnet_no_am_dcn]", f"task.weights.uwnet_no_am_dcn={weights}",
                               f"out_dir={tmp_path / 'out'}", *SMALL])
    report = run(cfg)
    assert set(report["results"]) == {"uwnet_no_am_dcn"} and not report["skipped"]
    assert report["results"]["uwnet_no_am_dcn"]["overall"]["pairs"] == 2
    assert "| UWNet w/o AM-DCN |" in (tmp_path / "out" / "table.md").read_text()
    # a weights path given directly as an extractor: its pictures are named after the file, inside out_dir
    cfg = compose("evaluate", ["task=matching", "dataset=upatches", f"dataset.root={src}", "dataset.num_images=1",
                               f"extractors=[{weights}]", f"out_dir={tmp_path / 'out2'}", *SMALL])
    report = run(cfg)
    assert report["pictures"] and all(p.startswith("matches/no_am_dcn.pt_") for p in report["pictures"])


def test_rotation_tta_rows_beside_the_plain_ones(tmp_path):
    src = write_images(tmp_path / "src", 2)
    common = ["task=matching", "dataset=upatches", f"dataset.root={src}", "dataset.num_images=2",
              "extractors=[orb,xfeat]", *SMALL]
    cfg = compose("evaluate", [*common, "task.rotation_tta=[none,c4,c4best]", f"out_dir={tmp_path / 'out'}"])
    report = run(cfg)
    assert list(report["results"]) == ["orb", "orb+c4", "orb+c4best", "xfeat", "xfeat+c4", "xfeat+c4best"]
    table = (tmp_path / "out" / "table.md").read_text()
    assert "| ORB + C4 TTA |" in table and "| XFeat + C4 TTA |" in table and "| XFeat + C4 best rotation |" in table
    # one rotation's keypoints, not the pool's
    best = report["results"]["xfeat+c4best"]["overall"]["keypoints"]
    assert best < report["results"]["xfeat+c4"]["overall"]["keypoints"]
    # the plain rows equal a run without the option (image 2 and the upright reference are shared)
    alone = run(compose("evaluate", [*common, f"out_dir={tmp_path / 'alone'}"]))
    assert alone["results"]["xfeat"]["overall"] == report["results"]["xfeat"]["overall"]
    # the C4 reference holds the four rotations' keypoints
    assert report["results"]["xfeat+c4"]["overall"]["keypoints"] > report["results"]["xfeat"]["overall"]["keypoints"]
    with pytest.raises(ValueError, match="task.rotation_tta must be one of .* or a list of them, got 'c8'"):
        run(compose("evaluate", [*common, "task.rotation_tta=c8", f"out_dir={tmp_path / 'bad'}"]))
