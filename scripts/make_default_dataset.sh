#!/usr/bin/env bash
# Training data of the shipped default model: the built-in part library ONLY (never ../shared).
# Every built-in part at several random dimension draws (part seeds), piles from a few parts to
# several layers deep. Scene seeds SEED_BASE+ for training (100000 for the first set, 200000 for
# later ones), 800000+ for the built-in validation set (held-out part seed 99), so they never
# collide with the per-part (500000-599999) or IPA test seeds (900000+).
#   usage: scripts/make_default_dataset.sh OUT_DIR [SCENES_PER_PART_SEED] [PART_SEEDS]
#                                          [FIRST_PART_SEED] [SEED_BASE] [dense]
# With "dense", every draw also gets one scene of a full bin, 1 to 2.5 layers deep
# (`dense_parts_range`: up to 100 copies where the default range stops at 60), in
# OUT_DIR/train/PART_pSEED_dense, scene seed SEED_BASE + i * 1000 + 500.
# A later set (FIRST_PART_SEED > 0: new dimension draws, new scene seeds) writes no validation
# scenes, so the validation set stays the one the first set made.
#   first set (sessions 1-7): scripts/make_default_dataset.sh /work/data_default 7 6
#   second set (session 8):   scripts/make_default_dataset.sh /work/data_default 7 12 6 200000
#   third set (session 27):   scripts/make_default_dataset.sh /work/data_default2 2 10 18 300000
#     (its scene seeds overlap the second set's upper half, for other parts and draws)
#   fourth set (session 28):  scripts/make_default_dataset.sh /work/data_default3 2 10 28 600000
#     (14 min with 2 workers on a 2-vCPU AMD EPYC; scene seeds 600000-739000)
#   fifth set (session 35):   scripts/make_default_dataset.sh /work/data_dense 1 10 38 1100000 dense
#     (one default and one full-bin scene per draw; scene seeds 1100000-1239500)
set -euo pipefail
OUT=${1:?output folder}
PER=${2:-7}
SEEDS=${3:-6}
FIRST=${4:-0}
BASE=${5:-100000}
DENSE=${6:-}
PY=${PY:-.venv/bin/python}
PARTS=$($PY -c "from fpcc_ros.training.parts import BUILTIN_PARTS; print(' '.join(BUILTIN_PARTS))" 2>/dev/null)
i=0
for part in $PARTS; do
  for ps in $(seq "$FIRST" $((FIRST + SEEDS - 1))); do
    $PY -m fpcc_ros.cli synth --part "$part" --part-seed "$ps" --scenes "$PER" \
        --seed $((BASE + i * 1000)) --out "$OUT/train/${part}_p${ps}" --workers 2
    if [ "$DENSE" = dense ]; then
      range=$($PY -c "from fpcc_ros.training.synth import dense_parts_range, resolve_part; print(*dense_parts_range(resolve_part('$part', $ps)))")
      $PY -m fpcc_ros.cli synth --part "$part" --part-seed "$ps" --scenes 1 --parts $range \
          --seed $((BASE + i * 1000 + 500)) --out "$OUT/train/${part}_p${ps}_dense" --workers 2
    fi
    i=$((i + 1))
  done
  if [ "$FIRST" -eq 0 ]; then
    # validation: one held-out dimension draw per part
    $PY -m fpcc_ros.cli synth --part "$part" --part-seed 99 --scenes 2 \
        --seed $((800000 + i * 1000)) --out "$OUT/val/${part}_p99" --workers 2
  fi
done
