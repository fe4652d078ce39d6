"""`evaluate.py task=synthesis` end to end on a tiny config, plus its helpers."""

import csv

import cv2
import numpy as np
import pytest
from conftest import compose

from ruslam.data.procedural import ProceduralRGBD
from ruslam.eval.quality import quality
from ruslam.eval.synthesis_report import fit, select_indices, to_uint8
from ruslam.evaluate import evaluate

H, W = 48, 64


def _reference(folder, n=3):
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):
        img = np.zeros((40, 40, 3), np.uint8)  # BGR on disk: a blue-green scene
        img[...] = (170, 140, 30)
        img += rng.integers(0, 60, (40, 40, 3), dtype=np.uint8)
        cv2.imwrite(str(folder / f"{i}.png"), img)
    return folder


def _cfg(tmp_path, extra=()):
    return compose("evaluate", ["task=synthesis", "dataset.num_images=4", f"dataset.height={H}",
                                f"dataset.width={W}", f"out_dir={tmp_path / 'run'}", "task.grid_rows=2", *extra])


def test_table_csv_and_grid_with_a_real_reference(tmp_path):
    ref = _reference(tmp_path / "real")
    cfg = _cfg(tmp_path, [f"dataset.reference={ref}", "task.background_light.num_images=3",
                          "task.background_light.regions_per_image=2"])
    out = evaluate(cfg)
    run = tmp_path / "run"
    results = out["results"]
    assert set(results) == {"in_air", "ours", "baseline", "real"}
    assert results["real"]["n"] == 3 and results["ours"]["n"] == 4

    # The in-air row is the plain mean of the metrics of the source images (recomputed here independently).
    source = ProceduralRGBD(num_images=4, height=H, width=W, seed=cfg.seed)
    in_air = [quality(to_uint8(source[i]["image"])) for i in range(4)]
    assert results["in_air"]["mean"]["uiqm"] == pytest.approx(np.mean([q["uiqm"] for q in in_air]), rel=1e-9)

    # Realism: |mean - real mean| per metric.
    for name in ("in_air", "ours", "baseline"):
        diff = abs(results[name]["mean"]["uciqe"] - results["real"]["mean"]["uciqe"])
        assert results[name]["realism"]["abs_diff"]["uciqe"] == pytest.approx(diff)

    md = (run / "table.md").read_text()
    for label in ("In-air", "Ours (eq. 4)", "UWCNN-style (eq. 1)", "Real (real)", "Distance to real", "UIConM"):
        assert label in md
    rows = list(csv.DictReader((run / "table.csv").open()))
    assert [r["method"] for r in rows] == ["In-air", "Ours (eq. 4)", "UWCNN-style (eq. 1)", "Real (real)"]
    assert float(rows[1]["uism"]) == pytest.approx(results["ours"]["mean"]["uism"], abs=1e-6)
    assert float(rows[2]["distance_to_real"]) == pytest.approx(results["baseline"]["realism"]["distance"], abs=1e-6)
    assert rows[3]["distance_to_real"] == ""

    grid = cv2.imread(str(run / "grid.png"))
    assert grid.shape[:2] == (22 + 2 * (H + 4), 6 * (W + 4))  # in-air | 3 water types | baseline | real
    assert not list(run.glob(".*tmp*"))


def test_without_reference_no_distance_and_five_columns(tmp_path):
    out = evaluate(_cfg(tmp_path))
    assert set(out["results"]) == {"in_air", "ours", "baseline"}
    assert "Distance to real" not in (tmp_path / "run" / "table.md").read_text()
    assert cv2.imread(str(tmp_path / "run" / "grid.png")).shape[1] == 5 * (W + 4)
    # ours differs from in-air and from the baseline (the synthesis actually ran)
    means = {k: v["mean"]["uciqe"] for k, v in out["results"].items()}
    assert means["ours"] != means["in_air"] and means["ours"] != means["baseline"]


def test_bad_reference_fails_before_writing_anything(tmp_path):
    with pytest.raises(FileNotFoundError, match="dataset.reference=.*missing: no such folder"):
        evaluate(_cfg(tmp_path, [f"dataset.reference={tmp_path / 'missing'}",
                                 f"dataset.background_light={_reference(tmp_path / 'light', 10)}"]))
    assert not (tmp_path / "run" / "table.md").exists()
    with pytest.raises(ValueError, match="Unknown Jerlov water type"):
        evaluate(_cfg(tmp_path, ["task.grid_water_types=[I,XX,III]"]))


def test_fit_crops_to_aspect_then_resizes():
    image = np.zeros((100, 100, 3), np.float32)
    image[:, :, 0] = np.arange(100)[:, None]  # rows 0..99
    out = fit(image, 30, 60)  # 2:1 -> keep the middle 50 rows (25..74)
    assert out.shape == (30, 60, 3)
    assert 24 <= out[0, 0, 0] <= 27 and 72 <= out[-1, 0, 0] <= 75


def test_select_indices_is_a_seeded_subset():
    assert select_indices(5, 200, 0) == [0, 1, 2, 3, 4]
    picked = select_indices(1449, 200, 0)
    assert len(set(picked)) == 200 and picked == sorted(picked) and picked == select_indices(1449, 200, 0)
    assert picked != select_indices(1449, 200, 1)


def test_nyu_config_reads_the_paper_split(tmp_path):
    import h5py

    rng = np.random.default_rng(0)
    mat = tmp_path / "nyu.mat"
    with h5py.File(mat, "w") as f:  # MATLAB layout: (N,3,W,H) and (N,W,H)
        f["images"] = rng.integers(0, 256, (6, 3, 40, 30), dtype=np.uint8)
        f["depths"] = (0.5 + 4 * rng.random((6, 40, 30))).astype(np.float32)
    cfg = compose("evaluate", ["task=synthesis", "dataset=synthesis_nyu", f"dataset.path={mat}",
                               "dataset.source.num_test=3", "dataset.height=24", "dataset.width=32",
                               f"out_dir={tmp_path / 'run'}", "task.grid_rows=1"])
    out = evaluate(cfg)
    assert out["results"]["in_air"]["n"] == 3  # the test split, not all six
    assert "NYU-Depth-v2 test split" in (tmp_path / "run" / "table.md").read_text()


def test_rgbd_folder_config_on_real_nyu_samples(shared_data, tmp_path):
    cfg = compose("evaluate", ["task=synthesis", "dataset=synthesis_rgbd",
                               f"dataset.root={shared_data / 'rgbd' / 'nyu_samples'}", "dataset.height=60",
                               "dataset.width=80", f"out_dir={tmp_path / 'run'}", "task.grid_rows=1"])
    out = evaluate(cfg)
    assert out["results"]["ours"]["n"] == 2
