#!/usr/bin/env bash
# A 1000-step probe (issue 55): the CPU configuration's 6000-step cosine run of one arm on Task 1 (or $TASK), stopped once its
# 1000-step checkpoint is saved, then the first-chunk check on 20 held-out layouts, raw and through the codec.
#   bash docs/learning-curve/v3/probe_1000.sh NAME DATA_ROOT SEED FLAGS...
set -uo pipefail
source .venv/bin/activate
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 MUJOCO_GL=egl HF_HUB_OFFLINE=1
NAME=$1; DATA=$2; SEED=$3; shift 3
T=${TASK:-PickPlaceFixedBin-v0}  # TASK=PickPlaceRandomBin-v0 for Task 2
OUT=outputs/probe_1000/$NAME
CK=$OUT/checkpoints/001000/pretrained_model
mkdir -p outputs/probe_1000
if [ ! -f $CK/model.safetensors ]; then
  # A folder of this name without its checkpoint is another (or an unfinished) run: never deleted here.
  [ -e $OUT ] && { echo "$OUT exists without checkpoints/001000; move it or choose another NAME" >&2; exit 1; }
  condground train --policy.type=act_modified --policy.device=cpu --policy.push_to_hub=false \
    $(python -m lerobot_condground.core.training) --dataset.repo_id=local/$T --dataset.root=$DATA \
    --steps=6000 --save_freq=1000 --log_freq=100 --num_workers=0 --wandb.enable=false --seed=$SEED \
    --output_dir=$OUT "$@" > $OUT.log 2>&1 &
  PID=$!
  while kill -0 $PID 2>/dev/null; do
    if [ -f $CK/model.safetensors ] && [ -f $OUT/checkpoints/001000/training_state/training_step.json ]; then sleep 5; kill $PID; break; fi
    sleep 10
  done
  wait $PID 2>/dev/null
fi
python docs/learning-curve/v3/first_chunk_check.py --task=$T --layouts=20 $CK > $OUT.chunk.txt 2>&1
python docs/learning-curve/v3/first_chunk_check.py --task=$T --layouts=20 --camera_codec=video $CK >> $OUT.chunk.txt 2>&1
grep "r = " $OUT.chunk.txt
grep -o "l1_loss:[0-9.]*" $OUT.log | tail -1
