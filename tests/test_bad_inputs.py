"""Every row of docs/ERRORS.md, checked against what the code now does.

A command row (`python train.py ...`, `python evaluate.py ...`, `python -m ruslam.features ...`) must exit 2 with
exactly one stderr line,
``error: <the documented sentence>``, no traceback and no file written; a Python row must raise
`ruslam.errors.InputError` with the documented sentence. In the table, ``$TMP`` is a scratch folder holding
``empty/`` (an empty folder), ``images/`` (``a.png``, ``b.png``), ``pairs.txt`` (``a.png b.png``),
``bad_pairs.txt`` (``a.png``), ``not_weights.pt`` and ``not_a_mat.mat`` (text files), and ``…`` stands for any text
(lists that grow when an extractor is registered). The fast test runs the command rows in this process through
the same `run_cli`; the slow one runs the real entry points in subprocesses.
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import ROOT, compose

from ruslam.cli import run_cli
from ruslam.errors import InputError

ERRORS_MD = ROOT / "docs" / "ERRORS.md"
ROW = re.compile(r"^\| (\d+) \| `(.+?)` \| ``(.+)`` \|$")


def table_rows() -> list[tuple[str, str, str]]:
    rows = [ROW.match(line) for line in ERRORS_MD.read_text().splitlines()]
    return [(m[1], m[2], m[3]) for m in rows if m]


ROWS = table_rows()
FEATURES = "python -m ruslam.features "
COMMANDS = [r for r in ROWS if r[1].startswith("python ") and not r[1].startswith(FEATURES)]
FEATURE_COMMANDS = [r for r in ROWS if r[1].startswith(FEATURES)]
CALLS = [r for r in ROWS if not r[1].startswith("python ")]


def matches(documented: str, actual: str, tmp: Path) -> bool:
    pattern = ".*".join(re.escape(part) for part in documented.replace("$TMP", str(tmp)).split("…"))
    return re.fullmatch(pattern, actual, re.DOTALL) is not None


def make_scratch(tmp_path: Path) -> None:
    """The files the table's ``$TMP`` holds (shared with bench/bad_inputs.py)."""
    (tmp_path / "empty").mkdir()
    (tmp_path / "images").mkdir()
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(tmp_path / "images" / name), np.random.default_rng(0).integers(0, 256, (64, 64, 3), np.uint8))
    (tmp_path / "pairs.txt").write_text("a.png b.png\n")
    (tmp_path / "bad_pairs.txt").write_text("a.png\n")
    (tmp_path / "not_weights.pt").write_text("not a torch file\n")
    (tmp_path / "not_a_mat.mat").write_text("not a MATLAB file\n")


@pytest.fixture
def scratch(tmp_path, monkeypatch) -> Path:
    make_scratch(tmp_path)
    for var in ("EUROC_ROOT", "TUM_ROOT", "AQUALOC_HARBOR_ROOT", "AQUALOC_ARCHAEO_ROOT", "RUSLAM_DEBUG"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("RUSLAM_CACHE", str(tmp_path / "cache"))
    return tmp_path


def test_the_table_has_at_least_15_rows_across_entry_points_and_readers():
    assert len(ROWS) >= 15 and [r[0] for r in ROWS] == [str(i) for i in range(1, len(ROWS) + 1)]
    kinds = {r[1].split()[1] if r[1].startswith("python ") else r[1].split("(")[0] for r in ROWS}
    assert {"train.py", "evaluate.py", "load_extractor"} <= kinds


def _written(out: Path) -> list[str]:
    return sorted(str(p.relative_to(out)) for p in out.rglob("*")) if out.exists() else []


@pytest.mark.parametrize(("number", "command", "message"), COMMANDS, ids=[r[0] for r in COMMANDS])
def test_command_row_in_process(number, command, message, scratch, capsys):
    from ruslam.evaluate import evaluate
    from ruslam.train import train

    words = shlex.split(command.replace("$TMP", str(scratch)))
    entry, overrides = words[1], words[2:]
    out = scratch / "run"
    cfg = compose(entry.removesuffix(".py"), [*overrides, f"out_dir={out}"])
    with pytest.raises(SystemExit) as exit_info:
        run_cli(train if entry == "train.py" else evaluate, cfg)
    err = capsys.readouterr().err
    assert exit_info.value.code == 2
    assert err.count("\n") == 1 and err.startswith("error: "), err
    assert matches(message, err[len("error: "):].rstrip("\n"), scratch), err
    assert [p for p in _written(out)] == [], "a bad input left files behind"


@pytest.mark.parametrize(("number", "command", "message"), FEATURE_COMMANDS, ids=[r[0] for r in FEATURE_COMMANDS])
def test_features_row_in_process(number, command, message, scratch, capsys):
    from ruslam.features.__main__ import main

    before = _written(scratch)
    with pytest.raises(SystemExit) as exit_info:
        main(shlex.split(command.replace("$TMP", str(scratch)))[3:])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2
    assert err.count("\n") == 1 and err.startswith("error: "), err
    assert matches(message, err[len("error: "):].rstrip("\n"), scratch), err
    assert _written(scratch) == before, "a bad input left files behind"


@pytest.mark.parametrize(("number", "call", "message"), CALLS, ids=[r[0] for r in CALLS])
def test_python_row(number, call, message, scratch):
    from ruslam import load_extractor
    from ruslam.data.hpatches import HPatches
    from ruslam.data.nyu import NYUDepthV2
    from ruslam.data.readers import read_aqualoc, read_euroc, read_image_folder, read_tum
    from ruslam.data.rgbd_folder import RGBDFolder

    namespace = dict(np=np, load_extractor=load_extractor, HPatches=HPatches, NYUDepthV2=NYUDepthV2,
                     RGBDFolder=RGBDFolder, read_euroc=read_euroc, read_tum=read_tum, read_aqualoc=read_aqualoc,
                     read_image_folder=read_image_folder)
    with pytest.raises(InputError) as err:
        eval(call.replace("$TMP", str(scratch)), namespace)  # noqa: S307 (the table's own expressions)
    assert matches(message, str(err.value), scratch), str(err.value)


@pytest.mark.slow
@pytest.mark.parametrize(("number", "command", "message"), COMMANDS + FEATURE_COMMANDS,
                         ids=[r[0] for r in COMMANDS + FEATURE_COMMANDS])
def test_command_row_through_the_entry_point(number, command, message, scratch):
    words = shlex.split(command.replace("$TMP", str(scratch)))
    run_dir = scratch / "run"
    hydra = [] if command.startswith(FEATURES) else [f"hydra.run.dir={run_dir}"]
    before = _written(scratch)
    done = subprocess.run([sys.executable, *words[1:], *hydra], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2, done.stderr[-2000:]
    assert "Traceback" not in done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), done.stderr[-2000:]
    assert matches(message, lines[0][len("error: "):], scratch), lines[0]
    # Hydra's own record of the run (.hydra/ and the job log) is all that may exist
    assert [p for p in _written(run_dir) if not (p.startswith(".hydra") or p.endswith(".log"))] == []
    assert [p for p in _written(scratch) if p not in before and not p.startswith("run")] == []


def test_config_checks_run_before_torch_is_imported(tmp_path):
    """Why a bad input is reported in seconds: the checks of every default config import no heavy library."""
    code = f"""
import sys
sys.path.insert(0, {str(ROOT / "tests")!r})
from conftest import compose
from ruslam.config_checks import check_evaluate, check_train
check_train(compose("train", ["out_dir={tmp_path}"]))
for task in ("synthesis", "matching", "slam"):
    check_evaluate(compose("evaluate", [f"task={{task}}", "out_dir={tmp_path}"]))
print(sorted(m for m in ("torch", "torchvision", "pytorch_lightning", "gtsam", "evo", "kornia") if m in sys.modules))
"""
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "[]", done.stdout
