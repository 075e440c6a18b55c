#!/usr/bin/env bash
# From-scratch backbones on a CPU: act_modified `standard` on Task 1 (100 clean demonstrations, 96x128),
# once with LeRobot's frozen batch norm (an identity without pretrained weights) and once with group norm,
# trained side by side for the same wall-clock budget (one core each, fp32), then every saved checkpoint
# evaluated on clean scenes with `condground sweep`. Writes one CSV per backbone norm under $CSV_DIR:
# minutes,steps,samples,success,n,ci_low,ci_high (95 % Wilson intervals).
#
#   MINUTES=55 EVERY=250 EVAL_EVERY=500 EPISODES=50 bash docs/measurements/backbone_norm_check.sh
#
# bf16 autocast (--policy.use_amp=true) is left off on purpose: it is fast only where the CPU has
# AVX-512 BF16 or AMX; on an AVX2-only CPU a ResNet-18 step was 22x slower under it than in fp32.
set -euo pipefail
OUT=${OUT:-outputs/learn}
MINUTES=${MINUTES:-55}
EVERY=${EVERY:-250}          # steps between saved checkpoints
EVAL_EVERY=${EVAL_EVERY:-500}  # evaluated: checkpoints at multiples of this, and the last one
EPISODES=${EPISODES:-50}     # clean rollouts per checkpoint
BATCH=${BATCH:-32}
CSV_DIR=${CSV_DIR:-docs/learning-curve}
TASK=PickPlaceFixedBin-v0
DATA="$OUT/data/$TASK"
export MUJOCO_GL=${MUJOCO_GL:-egl} HF_HUB_OFFLINE=1 WANDB_MODE=disabled

[ -f "$DATA/meta/info.json" ] || condground record --env.task=$TASK --env.condition=clean \
  --env.observation_height=96 --env.observation_width=128 --dataset.repo_id=local/learn_t1 \
  --dataset.root="$DATA" --dataset.num_episodes=100 --progress=false

train() {  # name norm
  date +%s > "$OUT/$1.start"
  OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 timeout "${MINUTES}m" lerobot-train --policy.type=act_modified \
    --policy.variant=standard --policy.backbone_norm="$2" --policy.device=cpu --policy.push_to_hub=false \
    --policy.use_amp=false --policy.pretrained_backbone_weights=null --policy.dim_model=256 --policy.n_heads=8 \
    --policy.dim_feedforward=1024 --policy.n_encoder_layers=4 --policy.chunk_size=20 --policy.n_action_steps=20 \
    --policy.optimizer_lr=1e-4 --policy.optimizer_lr_backbone=1e-4 --dataset.repo_id=local/learn_t1 \
    --dataset.root="$DATA" --batch_size="$BATCH" --steps=100000 --save_freq="$EVERY" --log_freq=25 \
    --num_workers=0 --wandb.enable=false --seed=0 --output_dir="$OUT/$1" > "$OUT/$1.log" 2>&1 || true
}
for norm in frozen_batchnorm groupnorm; do
  [ -d "$OUT/t1_$norm/checkpoints" ] || train "t1_$norm" "$norm" &
done
wait

mkdir -p "$CSV_DIR"
for norm in frozen_batchnorm groupnorm; do
  last=$(ls -d "$OUT/t1_$norm"/checkpoints/[0-9]* | sort | tail -n 1)
  for ckpt in "$OUT/t1_$norm"/checkpoints/[0-9]*/pretrained_model; do
    step=$(basename "$(dirname "$ckpt")")
    [ $((10#$step % EVAL_EVERY)) = 0 ] || [ "$(dirname "$ckpt")" = "$last" ] || continue
    [ -f "$OUT/eval/$norm/$step/results.parquet" ] || condground sweep --policy.paths="$ckpt" \
      --env.task=$TASK --sweep.conditions=clean --eval.seeds=1 --eval.n_episodes="$EPISODES" \
      --output_dir="$OUT/eval/$norm/$step" --progress=false
  done
done

python - "$OUT" "$BATCH" "$CSV_DIR" "$TASK" <<'PY'
import re
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pandas as pd

from lerobot_condground.evaluation.results import read_table
from lerobot_condground.evaluation.statistics import cell_metrics

out, batch, csv_dir, task = Path(sys.argv[1]), int(sys.argv[2]), Path(sys.argv[3]), sys.argv[4]
fig, (ax_loss, ax_success) = plt.subplots(1, 2, figsize=(10, 3.6))
for norm in ("frozen_batchnorm", "groupnorm"):
    start = float((out / f"t1_{norm}.start").read_text())
    rows = []
    for results in sorted((out / "eval" / norm).glob("*/results.parquet")):
        saved = (out / f"t1_{norm}" / "checkpoints" / results.parent.name / "pretrained_model").stat().st_mtime
        m = cell_metrics(read_table(results)).iloc[0]
        step = int(results.parent.name)
        rows.append({"minutes": round((saved - start) / 60, 1), "steps": step, "samples": step * batch,
                     "success": m["success"], "n": int(m["success_n"]), "ci_low": m["success_low"],
                     "ci_high": m["success_high"], "p_pick": m["p_pick"]})
    curve = pd.DataFrame(rows).sort_values("steps")
    curve.to_csv(csv_dir / f"{task}_standard_{norm}.csv", index=False, float_format="%.4f")
    print(norm, "\n", curve.to_string(index=False))
    log = (out / f"t1_{norm}.log").read_text()
    # LeRobot writes the step rounded (1K, 2K, ...): a logged line is every --log_freq=25 steps.
    values = [float(v) for v in re.findall(r"step:\S+ .*?l1_loss:([0-9.]+)", log)]
    loss = pd.DataFrame({"steps": [25 * (i + 1) for i in range(len(values))], "l1_loss": values})
    loss.to_csv(csv_dir / f"{task}_standard_{norm}_loss.csv", index=False)
    ax_loss.plot(loss.steps, loss.l1_loss, label=norm)
    ax_success.errorbar(curve.minutes, 100 * curve.success, fmt="o-", label=norm, capsize=3,
                        yerr=[100 * (curve.success - curve.ci_low), 100 * (curve.ci_high - curve.success)])
ax_loss.set(xlabel="training steps (batch %d)" % batch, ylabel="training L1 loss (normalized actions)", yscale="log")
ax_success.set(xlabel="wall-clock minutes of training (one core each)", ylabel="clean success, % (95 % CI)", ylim=(-5, 105))
for ax in (ax_loss, ax_success):
    ax.grid(alpha=0.3)
    ax.legend()
fig.suptitle(f"act_modified standard from scratch, {task}, 96x128: backbone normalization")
fig.tight_layout()
fig.savefig(csv_dir / f"{task}_standard_backbone_norm.png", dpi=110)
PY
