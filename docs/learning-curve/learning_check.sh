#!/usr/bin/env bash
# The learning check of issue 3 (§6): standard ACT and full ACT-Modified trained on Task 1 from 100
# clean demonstrations, each evaluated under `clean` and `full_mixed` with the stock lerobot-eval.
# Needs a GPU: on a 2-core CPU one training step at ACT's size takes ~2.6 s.
#
#   DEVICE=cuda STEPS=20000 bash docs/learning-curve/learning_check.sh
#
# Expected direction (paper, Table 1): standard collapses under full_mixed, ACT-Modified holds.
set -euo pipefail
OUT=${OUT:-outputs/learning_check}
STEPS=${STEPS:-20000}
DEVICE=${DEVICE:-cuda}
EPISODES=${EPISODES:-50}
BACKBONE=${BACKBONE:-null}  # ResNet18_Weights.IMAGENET1K_V1 where torchvision can download it
export MUJOCO_GL=${MUJOCO_GL:-egl} HF_HUB_OFFLINE=1 WANDB_MODE=disabled

condground record --env.task=PickPlaceFixedBin-v0 --env.condition=clean --dataset.repo_id=local/t1_clean \
  --dataset.root="$OUT/data/t1_clean" --dataset.num_episodes=100

for variant in standard full; do
  if [ ! -d "$OUT/train/$variant/checkpoints/last" ]; then
    lerobot-train --policy.type=act_modified --policy.variant=$variant --policy.device="$DEVICE" \
      --policy.push_to_hub=false --policy.pretrained_backbone_weights="$BACKBONE" \
      --dataset.repo_id=local/t1_clean --dataset.root="$OUT/data/t1_clean" --batch_size=8 --steps="$STEPS" \
      --save_freq="$STEPS" --log_freq=500 --num_workers=8 --wandb.enable=false --output_dir="$OUT/train/$variant"
  fi
  for condition in clean full_mixed; do
    lerobot-eval --policy.path="$OUT/train/$variant/checkpoints/last/pretrained_model" --env.type=condground \
      --env.task=PickPlaceFixedBin-v0 --env.condition=$condition --eval.n_episodes="$EPISODES" \
      --eval.batch_size=10 --output_dir="$OUT/eval/$variant/$condition"
  done
done

python - "$OUT" <<'PY'
import json, sys
from pathlib import Path
from lerobot_condground.evaluation.stage_metrics import format_table, stage_metrics
out = Path(sys.argv[1])
rows = []
for variant in ("standard", "full"):
    for condition in ("clean", "full_mixed"):
        info = json.loads((out / "eval" / variant / condition / "eval_info.json").read_text())
        stages = [int(r) for r in info["per_task"][0]["metrics"]["max_rewards"]]
        rows.append((f"act_modified/{variant}", condition, stage_metrics(stages)))
print(format_table(rows, first_column="policy"))
PY
