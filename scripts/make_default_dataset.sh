#!/usr/bin/env bash
# Training data of the shipped default model: the built-in part library ONLY (never ../shared).
# Every built-in part at several random dimension draws (part seeds), piles from a few parts to
# several layers deep. Scene seeds 100000+ for training, 800000+ for the built-in validation set
# (held-out part seeds), so they never collide with the IPA validation seeds (900000+).
#   usage: scripts/make_default_dataset.sh OUT_DIR [SCENES_PER_PART_SEED] [PART_SEEDS]
set -euo pipefail
OUT=${1:?output folder}
PER=${2:-7}
SEEDS=${3:-6}
PY=${PY:-.venv/bin/python}
PARTS=$($PY -c "from fpcc_ros.training.parts import BUILTIN_PARTS; print(' '.join(BUILTIN_PARTS))" 2>/dev/null)
i=0
for part in $PARTS; do
  for ps in $(seq 0 $((SEEDS - 1))); do
    $PY -m fpcc_ros.cli synth --part "$part" --part-seed "$ps" --scenes "$PER" \
        --seed $((100000 + i * 1000)) --out "$OUT/train/${part}_p${ps}" --workers 2
    i=$((i + 1))
  done
  # validation: one held-out dimension draw per part
  $PY -m fpcc_ros.cli synth --part "$part" --part-seed 99 --scenes 2 \
      --seed $((800000 + i * 1000)) --out "$OUT/val/${part}_p99" --workers 2
done
