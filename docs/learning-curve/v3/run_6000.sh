#!/usr/bin/env bash
# One protocol-length run of an arm (the CPU configuration's 6000-step cosine run, a checkpoint every 1000 steps),
# resumed from its last checkpoint when its folder holds one; the first-chunk check on 20 held-out layouts of each
# checkpoint it saves, as it saves it.
#   TASK=PickPlaceRandomBin-v0 bash docs/learning-curve/v3/run_6000.sh NAME DATA_ROOT SEED FLAGS...
set -uo pipefail
source .venv/bin/activate
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 MUJOCO_GL=egl HF_HUB_OFFLINE=1
NAME=$1; DATA=$2; SEED=$3; shift 3
T=${TASK:-PickPlaceFixedBin-v0}
OUT=outputs/runs_6000/$NAME
mkdir -p outputs/runs_6000
if [ -f $OUT/checkpoints/last/pretrained_model/train_config.json ]; then
  condground train --config_path=$OUT/checkpoints/last/pretrained_model/train_config.json --resume=true >> $OUT.log 2>&1 &
else
  [ -e $OUT ] && { echo "$OUT exists without a checkpoint; move it or choose another NAME" >&2; exit 1; }
  condground train --policy.type=act_modified --policy.device=cpu --policy.push_to_hub=false \
    $(python -m lerobot_condground.core.training) --dataset.repo_id=local/$T --dataset.root=$DATA \
    --steps=6000 --save_freq=1000 --log_freq=100 --num_workers=0 --wandb.enable=false --seed=$SEED \
    --output_dir=$OUT "$@" > $OUT.log 2>&1 &
fi
PID=$!
check() {
  for CK in $OUT/checkpoints/0*/pretrained_model; do
    [ -f $CK/model.safetensors ] && [ -f $CK/../training_state/training_step.json ] || continue
    STEP=$(basename $(dirname $CK))
    [ -f $OUT.chunk_$STEP.txt ] || python docs/learning-curve/v3/first_chunk_check.py --task=$T --layouts=20 $CK > $OUT.chunk_$STEP.txt 2>&1
  done
}
while kill -0 $PID 2>/dev/null; do check; sleep 30; done
check
grep -H "r = " $OUT.chunk_*.txt
