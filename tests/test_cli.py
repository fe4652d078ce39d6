import subprocess
import sys

from conftest import ROOT


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
