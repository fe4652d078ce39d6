import subprocess
import sys

import pytest
from conftest import ROOT
from hydra.utils import instantiate
from omegaconf import OmegaConf

from ruslam.cli import run_cli
from ruslam.errors import InputError


def test_bad_input_prints_one_sentence_and_exits_2(tmp_path):
    missing = tmp_path / "no_such_hpatches"
    proc = subprocess.run(
        [sys.executable, "evaluate.py", "task=matching", "dataset=hpatches", f"dataset.root={missing}",
         f"hydra.run.dir={tmp_path / 'run'}"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().startswith("error: ") and str(missing) in proc.stderr


def _raise(error):
    raise error


def test_run_cli_prints_input_errors_and_lets_bugs_keep_their_traceback(capsys, monkeypatch):
    monkeypatch.delenv("RUSLAM_DEBUG", raising=False)
    # an InputError raised inside a Hydra _target_ arrives wrapped in InstantiationException: unwrapped
    conf = {"_target_": "ruslam.data.rgbd_folder.RGBDFolder", "root": "/no/such/folder"}
    with pytest.raises(SystemExit) as exit_info:
        run_cli(instantiate, conf)
    assert exit_info.value.code == 2
    assert capsys.readouterr().err == "error: RGB-D folder /no/such/folder does not exist.\n"
    # an unset ??? value is named by its key
    cfg = OmegaConf.create({"dataset": {"root": "???"}})
    with pytest.raises(SystemExit):
        run_cli(lambda c: c.dataset.root, cfg)
    assert capsys.readouterr().err == "error: dataset.root is not set: pass dataset.root=/path/to/folder\n"
    # programming errors, bare or wrapped by Hydra, are not input errors
    for bug in (KeyError("depth"), TypeError("unsupported operand")):
        with pytest.raises(type(bug)):
            run_cli(_raise, bug)
    with pytest.raises(Exception, match="unexpected keyword argument"):
        run_cli(instantiate, {"_target_": "ruslam.data.rgbd_folder.RGBDFolder", "root": "x", "typo": 1})
    assert capsys.readouterr().err == ""
    monkeypatch.setenv("RUSLAM_DEBUG", "1")
    with pytest.raises(InputError):
        run_cli(_raise, InputError("shown with its traceback"))
