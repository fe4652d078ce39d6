"""How long a user waits for the sentence: every command row of docs/ERRORS.md run through its entry point.

    nice .venv/bin/python bench/bad_inputs.py [--rows 1,12,20]

Wall time from process start to exit (status 2) per row, against a baseline measured in the same run: a process
that only imports what building a Trainer or a model needs (torch, Lightning, torchvision), i.e. the least a
check made after building them would cost. The bound is 10 s per bad input on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from test_bad_inputs import COMMANDS, FEATURE_COMMANDS, make_scratch  # noqa: E402 (the table's own parser)

BASELINE = "import torch, torchvision, pytorch_lightning"


def timed(args: list[str], env_tmp: Path) -> tuple[float, int]:
    start = time.perf_counter()
    done = subprocess.run(args, cwd=ROOT, capture_output=True, text=True,
                          env={"PATH": "/usr/bin:/bin", "HOME": str(env_tmp), "RUSLAM_CACHE": str(env_tmp / "c"),
                               "OMP_NUM_THREADS": "1"})
    return time.perf_counter() - start, done.returncode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", help="comma-separated row numbers (default: every command row)")
    args = parser.parse_args()
    rows = [r for r in COMMANDS + FEATURE_COMMANDS if not args.rows or r[0] in args.rows.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        make_scratch(tmp)
        baseline, _ = timed([sys.executable, "-c", BASELINE], tmp)
        print(f"baseline ({BASELINE}): {baseline:.2f} s\n")
        print("| # | command | exit | seconds | ratio to baseline |\n|---|---|---|---|---|")
        worst = 0.0
        for number, command, _ in rows:
            words = shlex.split(command.replace("$TMP", str(tmp)))
            hydra = [] if words[1] == "-m" else [f"hydra.run.dir={tmp / 'run'}"]
            seconds, code = timed([sys.executable, *words[1:], *hydra], tmp)
            worst = max(worst, seconds)
            print(f"| {number} | `{command}` | {code} | {seconds:.2f} | x{seconds / baseline:.2f} |")
        again, _ = timed([sys.executable, "-c", BASELINE], tmp)
        print(f"\nslowest: {worst:.2f} s (bound: 10 s); baseline again: {again:.2f} s")


if __name__ == "__main__":
    main()
