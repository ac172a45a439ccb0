#!/usr/bin/env bash
# The per-part workflow the README promises, end to end, with the settings behind its figures:
# synth (train + validation) -> fine-tune the shipped model or $INIT (30 min) -> export -> calibrate on
# the validation scenes -> eval on separate test scenes (made with seeds never used above).
#   usage: scripts/per_part_workflow.sh MESH SCALE NAME WORK_DIR [TEST_DIR]
#   e.g.   scripts/per_part_workflow.sh ../shared/data/meshes/IPAGearShaft.stl 0.5 gear_shaft /work/part
# Scene folders that already hold a synth.json are kept (generation is deterministic per seed).
set -euo pipefail
MESH=${1:?mesh}; SCALE=${2:?scale}; NAME=${3:?name}; WORK=${4:?work dir}; TEST=${5:-}
PY=${PY:-.venv/bin/python}
MINUTES=${MINUTES:-30}
INIT=${INIT:-default}   # the weights to fine-tune: default (the shipped model) or a .pt checkpoint
TRAIN_ARGS=${TRAIN_ARGS:-}   # more `fpcc train` options, e.g. "--normals" (later ones win)
fpcc() { $PY -m fpcc_ros.cli "$@"; }
synth() {  # OUT SCENES SEED [extra synth options]
  local out=$1 scenes=$2 seed=$3; shift 3
  [ -f "$out/synth.json" ] || fpcc synth --mesh "$MESH" --scale "$SCALE" --out "$out" \
                                         --scenes "$scenes" --seed "$seed" "$@"
}
D=$WORK/data/$NAME
fpcc part-info "$MESH" --scale "$SCALE"
synth "$D/train" 40 500000
synth "$D/train2" 60 520000
# 12 validation piles: calibrating on 4 picked settings that did worse on test piles
synth "$D/val" 12 510000 --parts 30 60
# lr 1e-3: on a machine where 17-19 of the 45 epochs fit in 30 minutes, the gear shaft's
# validation F1 0.624 against 0.560 with 5e-4 (test 0.60 vs 0.55; same data, same day)
fpcc train --data "$D/train" "$D/train2" --val "$D/val" --out "$WORK/runs/$NAME" \
           --init "$INIT" --epochs 45 --time-limit "$MINUTES" --anneal-by-time --lr 1e-3 \
           --val-every 5 $TRAIN_ARGS
# the last checkpoint, not "best": best is ranked by validation F1 at the training run's fixed
# θ and γ, which calibration changes next (on the gear shaft it picked epoch 6 of 30)
fpcc export "$WORK/runs/$NAME/checkpoint_last.pt" --out "$WORK/models/$NAME.onnx" --name "$NAME"
# concave creases cut or not (the exported card starts with them off): on the gear shaft, test
# piles F1 0.659 with them cut at 120 against 0.636 uncut at the calibrated settings (2026-12-05)
# it ends by trying other joins and finer voxels at the best settings (ring screw: join 2 -> 3,
# test piles F1 0.764 -> 0.788, 2026-12-08; gear shaft: voxel 0.1 -> 0.07 d_max, 0.752 -> 0.784
# at 1.8x the time, 2026-12-07)
fpcc calibrate "$WORK/models/$NAME.onnx" --data "$D/val" --fragment-creases 0 120 --write
if [ -n "$TEST" ]; then
  fpcc eval --data "$TEST" --model "$WORK/models/$NAME.onnx" --protocol both \
            --out "$WORK/eval_$NAME.json"
fi
