import json

import cv2
import pytest
from conftest import compose

from ruslam.eval.turbidity_report import run

TINY = ["task=turbidity", "dataset.num_images=1", "dataset.render_size=[96,128]", "dataset.size=[96,128]",
        "dataset.eval_size=[96,128]", "dataset.num_warps=2", "extractors=[orb,xfeat,uwnet_no_am_dcn]"]


def test_one_build_per_class_and_one_column_per_class(tmp_path):
    report = run(compose("evaluate", [*TINY, f"out_dir={tmp_path}"]))
    classes = ["I-III", "1C-5C", "7C-9C", "low light"]
    assert list(report["results"]) == classes and report["pairs"] == dict.fromkeys(classes, 2)
    # each class's settings reached its own build (recorded in the manifest)
    manifests = {c: json.loads((tmp_path / "upatches" / c.replace(" ", "_").replace("-", "_") / "upatches.json")
                               .read_text()) for c in classes}
    assert manifests["7C-9C"]["degrade"]["water_types"] == ["7C", "9C"]
    assert manifests["low light"]["degrade"]["low_light"] == [0.3, 0.3]
    assert all(m["degrade"]["blur_length"] == 10 for m in manifests.values())  # full strength
    # the same scene in 5C at 30 % light is darker than in clear open-ocean water
    bright = cv2.imread(str(tmp_path / "upatches" / "I_III" / "v_000" / "1.ppm")).mean()
    dim = cv2.imread(str(tmp_path / "upatches" / "low_light" / "v_000" / "1.ppm")).mean()
    assert dim < 0.6 * bright
    table = (tmp_path / "table.md").read_text()
    assert "| Method | I-III (n=2) | 1C-5C (n=2) | 7C-9C (n=2) | low light (n=2) |" in table
    assert "| ORB |" in table and "| XFeat |" in table and "UWNet w/o AM-DCN (`uwnet_no_am_dcn`)" in table
    for c in classes:
        o = report["results"][c]["xfeat"]["overall"]
        assert o["pairs"] == 2 and 0 <= o["mma"] <= 100
    assert (tmp_path / "table.csv").read_text().count("\n") == 1 + 4 * 2 * 4  # header + class x method x part


def test_unknown_class_setting_is_one_sentence(tmp_path):
    with pytest.raises(ValueError, match=r"task.classes.murky has unknown setting\(s\) \['turbidity'\]"):
        run(compose("evaluate", [*TINY, f"out_dir={tmp_path}", "+task.classes.murky={turbidity:3}"]))
