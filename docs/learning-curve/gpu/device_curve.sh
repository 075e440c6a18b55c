#!/usr/bin/env bash
# Issue 27 §4: a larger configuration than the CPU's, trained on one GPU machine (16 cores, one H200) inside one
# device call: record the settled demonstrations on every core, train `standard` on both tasks at once on
# the GPU with `condground train` (LeRobot's loop), then `condground sweep` the last checkpoints on held-out
# clean layouts there (checkpoints this size cannot come back: 16 MiB a file). Everything that comes back is
# under $OUT: results (sweep parquets, training logs, configs) as one tarball, and this script's log.
#
#   OUT=/tmp/out DEVICE=cpu DEMOS=4 SHARDS=2 STEPS=20 EVERY=10 BATCH=4 LOADERS=1 EPISODES=2 POOL=2 \
#       bash docs/learning-curve/gpu/device_curve.sh          # the same path at toy scale on a CPU (about 4 minutes)
#
# The machine has PyTorch but not LeRobot or MuJoCo: docs/learning-curve/gpu/README.md says which wheels
# travel with the call (64 MiB in all, with the working tree) and gives the call itself.
# Each phase has a deadline (seconds from the start), so that whatever finished still comes back when the
# device call's limit is near: training is stopped at TRAIN_END and the checkpoints saved so far are swept.
set -uo pipefail
OUT=${OUT:?set OUT to the folder that comes back}
WORK=${WORK:-/tmp/condground}   # datasets and checkpoints: stay on the machine
DEVICE=${DEVICE:-cuda}
TASKS=${TASKS:-"PickPlaceFixedBin-v0 PickPlaceRandomBin-v0"}
VARIANT=${VARIANT:-standard}
SEED=${SEED:-0}
DEMOS=${DEMOS:-200}             # per task, recorded in SHARDS processes per task (seeds k*1000 onward)
SHARDS=${SHARDS:-8}
SIZE=${SIZE:-"144 192"}
STEPS=${STEPS:-1500}            # the cosine schedule ends here (about 14 steps/s a run there, two runs)
EVERY=${EVERY:-250}
BATCH=${BATCH:-32}
LOADERS=${LOADERS:-7}           # DataLoader workers per training run
EPISODES=${EPISODES:-50}        # held-out rollouts per checkpoint
POOL=${POOL:-3}                 # last checkpoints swept per run
TRAIN_END=${TRAIN_END:-390}     # seconds from the start: training is stopped here
SWEEP_END=${SWEEP_END:-570}     # and the sweeps here (300 rollouts took about 3 minutes there)
# The CPU configuration's levers (cosine, no dropout, no CVAE, drift demos, chunk 20 / execute 10) at ACT's
# own size: full-width ResNet-18, width 512, 4 encoder layers.
LARGE=${LARGE:-"--policy.backbone_width=64 --policy.dim_model=512 --policy.dim_feedforward=2048 --policy.n_encoder_layers=4"}
read -r H W <<< "$SIZE"
START=$(date +%s)
export MUJOCO_GL=${MUJOCO_GL:-egl} HF_HUB_OFFLINE=1 WANDB_MODE=disabled PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
mkdir -p "$OUT" "$WORK"
LOG=$OUT/run.log
say() { echo "[$(($(date +%s) - START)) s] $*" | tee -a "$LOG"; }
left() { local s=$(($1 - ($(date +%s) - START))); echo $((s > 1 ? s : 1)); }

say "machine: $(getconf _NPROCESSORS_ONLN) cores; $(python3 -c 'import torch; print(torch.__version__, torch.cuda.get_device_name() if torch.cuda.is_available() else "no GPU")' 2>&1)"

# Fail fast (a failed call leaves device time for a corrected one): rendering, the plugin, the accelerator.
if ! python3 -P -c "
import torch, mujoco, lerobot_condground.registration
mujoco.GLContext(64, 64).make_current()
assert '$DEVICE' != 'cuda' or torch.cuda.is_available(), 'no CUDA device'
" >> "$LOG" 2>&1; then
  say "checks failed: $(tail -3 "$LOG")"; ldconfig -p | grep -iE 'libegl|libopengl' >> "$LOG"; exit 1
fi

say "record $DEMOS drift demos per task at ${H}x${W}, $SHARDS shards a task"
for T in $TASKS; do
  for ((k = 0; k < SHARDS; k++)); do
    condground record --env.task="$T" --env.condition=clean --env.observation_height="$H" \
      --env.observation_width="$W" --dataset.repo_id="local/$T" --dataset.root="$WORK/data/${T}_$k" \
      --dataset.num_episodes=$((DEMOS / SHARDS)) --seed=$((k * 1000)) --drift.std=0.06 \
      > "$WORK/record_${T}_$k.log" 2>&1 &
  done
done
wait
# A merge copies every video (about 95 s for 200 episodes at 144x192 there): the tasks' merges at once.
for T in $TASKS; do
  roots=$(for ((k = 0; k < SHARDS; k++)); do printf '%s,' "$WORK/data/${T}_$k"; done)
  if ((SHARDS == 1)); then
    mv "$WORK/data/${T}_0" "$WORK/data/$T"
  else
    condground merge --roots="[${roots%,}]" --output.root="$WORK/data/$T" --output.repo_id="local/$T" \
      > "$WORK/merge_$T.log" 2>&1 || say "merge $T failed: $(tail -3 "$WORK/merge_$T.log")" &
  fi
done
wait
for T in $TASKS; do
  say "$T: $(python3 -c "import json,sys; i=json.load(open(sys.argv[1])); print(i['total_episodes'], 'episodes,', i['total_frames'], 'frames')" "$WORK/data/$T/meta/info.json" 2>&1)"
done

read -r -a CPU <<< "$(python3 -P -m lerobot_condground.core.training)"
say "train $VARIANT, $STEPS steps of batch $BATCH, until $TRAIN_END s"
for T in $TASKS; do
  run=$WORK/train/${T}_${VARIANT}_s$SEED
  mkdir -p "$WORK/train"
  # shellcheck disable=SC2086  # LARGE is a list of flags
  timeout --signal=INT --kill-after=20 "$(left "$TRAIN_END")" condground train --policy.type=act_modified \
    --policy.variant="$VARIANT" --policy.device="$DEVICE" --policy.push_to_hub=false "${CPU[@]}" $LARGE \
    --batch_size="$BATCH" --dataset.repo_id="local/$T" --dataset.root="$WORK/data/$T" \
    --dataset.video_backend=pyav --steps="$STEPS" --save_freq="$EVERY" --log_freq=100 \
    --num_workers="$LOADERS" --frame_cache_gb=4 --wandb.enable=false --seed="$SEED" --output_dir="$run" \
    > "$run.log" 2>&1 &
done
wait
say "trained: $(ls -d "$WORK"/train/*/checkpoints/0* 2>/dev/null | sed 's|.*/train/||' | tr '\n' ' ')"

say "sweep the last $POOL checkpoints of each run, $EPISODES held-out layouts each, until $SWEEP_END s"
jobs_=$(($(getconf _NPROCESSORS_ONLN) / (POOL * $(echo $TASKS | wc -w))))
for T in $TASKS; do
  run=$WORK/train/${T}_${VARIANT}_s$SEED
  for ckpt in $(ls -d "$run"/checkpoints/0* 2>/dev/null | tail -n "$POOL"); do
    step=$(basename "$ckpt")
    timeout "$(left "$SWEEP_END")" condground sweep --policy.path="$ckpt/pretrained_model" \
      --policy.device="$DEVICE" --env.task="$T" --env.observation_height="$H" --env.observation_width="$W" \
      --sweep.conditions=clean --eval.seeds=1 --eval.n_episodes="$EPISODES" --eval.seed_offset=1000000 \
      --workers="$((jobs_ > 0 ? jobs_ : 1))" --output_dir="$WORK/eval/${T}_${VARIANT}_s$SEED/$step" \
      --progress=false > "$WORK/eval_${T}_$step.log" 2>&1 &
  done
done
wait
say "swept: $(ls "$WORK"/eval/*/*/results.parquet 2>/dev/null | wc -l) checkpoints"

# What comes back: sweep tables, training logs and configs (no weights), the recording and sweep logs.
(cd "$WORK" && tar czf "$OUT/results.tgz" --exclude='*.safetensors' --exclude='*.pt' --exclude='*.pth' \
  --exclude='videos' --exclude='data/*/data' eval train ./*.log data/*/meta 2>/dev/null)
say "done: $(du -h "$OUT/results.tgz" | cut -f1) of results"
