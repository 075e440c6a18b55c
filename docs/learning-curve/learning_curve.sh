#!/usr/bin/env bash
# Learning curves on this machine: act_modified trained from scratch with the CPU training configuration
# (lerobot_condground/core/training.py) by LeRobot's training loop ($TRAIN: `condground train`, which
# holds decoded frames in memory, or the stock `lerobot-train`), runs side by side for the same
# wall-clock budget (one core each), then every saved checkpoint evaluated on clean scenes with
# `condground sweep`. Writes docs/learning-curve/<task>_<variant>.csv (minutes,steps,samples,success,n,
# ci_low,ci_high; 95 % Wilson intervals) and one plot per task.
#
#   RUNS="PickPlaceFixedBin-v0:standard PickPlaceRandomBin-v0:standard" MINUTES=60 bash docs/learning-curve/learning_curve.sh
#
# A run is TASK:VARIANT[:FLAG,FLAG...][@NAME] (extra lerobot-train flags, comma-separated, applied after
# the configuration's), named <task>_<variant>_<NAME>, or by its whole spec without @NAME. MINUTES is each run's total training time: rerunning skips
# finished evaluations and runs that had their MINUTES, and resumes the others from their last checkpoint.
# DEMOS clean demonstrations per task (default 100); other counts record into $OUT/data<DEMOS> (a rerun
# with more resumes the recording) and name their runs <task>_<variant>[_<flags>]_demos<DEMOS>.
# SIZE="H W" frames (default: the configuration's); another size records into $OUT/data[<DEMOS>]_<H>x<W>
# and appends _<H>x<W> to the run names. SERVO: the simulation's --env.servo for recording and evaluation
# (default interpolated; the curves made before 2026-11-30 used direct, and continue only with it).
set -euo pipefail
OUT=${OUT:-outputs/learning-curve}
RUNS=${RUNS:-"PickPlaceFixedBin-v0:standard PickPlaceRandomBin-v0:standard"}
MINUTES=${MINUTES:-60}
EVERY=${EVERY:-1000}        # steps between saved (and evaluated) checkpoints
EPISODES=${EPISODES:-50}    # clean rollouts per checkpoint
DEMOS=${DEMOS:-100}         # clean demonstrations per task
THREADS=${THREADS:-1}       # torch threads per training run
TRAIN=${TRAIN:-condground train}
CSV_DIR=${CSV_DIR:-docs/learning-curve}
SERVO=${SERVO:-interpolated}
# The configuration's cosine schedule anneals the learning rate to zero at STEPS: set it to what a run
# trains in MINUTES (about 3.5 steps/s for one run alone on a core of the AMX Xeon, bf16). The default
# keeps the rate near its peak for the whole budget, as the constant rate of the curves before 2026-12-01.
STEPS=${STEPS:-1000000}
export MUJOCO_GL=${MUJOCO_GL:-egl} HF_HUB_OFFLINE=1 WANDB_MODE=disabled
read -r -a TRAIN_FLAGS <<< "$(python -m lerobot_condground.core.training)"
CPU_SIZE=$(python -c "from lerobot_condground.core.training import CPU_FRAME_SIZE as s; print(s[0], s[1])")
SIZE=${SIZE:-$CPU_SIZE}

DATA=$OUT/data; SUFFIX=
[ "$DEMOS" = 100 ] || { DATA=$OUT/data$DEMOS; SUFFIX=_demos$DEMOS; }
[ "$SIZE" = "$CPU_SIZE" ] || { DATA=${DATA}_${SIZE/ /x}; SUFFIX=${SUFFIX}_${SIZE/ /x}; }
# A run named NAME (TASK:VARIANT[:FLAGS]@NAME) is <task>_<variant>_<NAME>; otherwise its spec names it.
name() {
  local spec=${1%%@*} tail=
  [ "$spec" = "$1" ] || { spec=${spec%%:*}:$(cut -d: -f2 <<< "$spec"); tail=_${1#*@}; }
  echo "$spec$tail$SUFFIX" | tr ':,=./' '_____'
}

episodes() { python -c "import json, sys; print(json.load(open(sys.argv[1]))['total_episodes'])" "$1" 2>/dev/null; }
for task in $(for run in $RUNS; do echo "${run%%:*}"; done | sort -u); do
  [ "$(episodes "$DATA/$task/meta/info.json")" = "$DEMOS" ] || condground record --env.task="$task" \
    --env.condition=clean --env.servo="$SERVO" --env.observation_height="${SIZE% *}" --env.observation_width="${SIZE#* }" \
    --dataset.repo_id="local/$task" --dataset.root="$DATA/$task" --dataset.num_episodes="$DEMOS" --progress=false
done

trained_s() { awk 'NF == 2 {t += $2 - $1} END {print t + 0}' "$1.start" 2>/dev/null || echo 0; }

for run in $RUNS; do
  IFS=: read -r task variant extra <<< "${run%%@*}"
  dir="$OUT/train/$(name "$run")"
  left=$((MINUTES * 60 - $(trained_s "$dir")))
  [ "$left" -gt 60 ] || continue
  mkdir -p "$OUT/train"
  if [ -d "$dir/checkpoints/last" ]; then  # a larger MINUTES: go on from the last checkpoint
    step=$((10#$(basename "$(readlink -f "$dir/checkpoints/last")")))
    args=(--config_path="$dir/checkpoints/last/pretrained_model/train_config.json" --resume=true
      --save_freq="$EVERY")
    log="$dir.resume-$step.log"
  else
    # shellcheck disable=SC2206
    args=(--policy.type=act_modified --policy.variant="$variant" --policy.device=cpu --policy.push_to_hub=false
      "${TRAIN_FLAGS[@]}" ${extra//,/ } --dataset.repo_id="local/$task" --dataset.root="$DATA/$task"
      --steps="$STEPS" --save_freq="$EVERY" --log_freq=50 --num_workers=0 --wandb.enable=false --seed=0
      --output_dir="$dir")
    log="$dir.log"
  fi
  # Each training segment appends "start stop" (epoch seconds): the curve's minutes add them up.
  (
    start=$(date +%s)
    # shellcheck disable=SC2086
    OMP_NUM_THREADS=$THREADS MKL_NUM_THREADS=$THREADS timeout "${left}s" $TRAIN "${args[@]}" > "$log" 2>&1 || true
    echo "$start $(date +%s)" >> "$dir.start"
  ) &
done
wait

for run in $RUNS; do  # one run's checkpoints after another, the runs side by side
  task=${run%%:*}
  dir="$OUT/train/$(name "$run")"
  for ckpt in "$dir"/checkpoints/[0-9]*/pretrained_model; do
    step=$(basename "$(dirname "$ckpt")")
    [ -f "$OUT/eval/$(name "$run")/$step/results.parquet" ] || condground sweep --policy.paths="$ckpt" \
      --env.task="$task" --env.servo="$SERVO" --sweep.conditions=clean --eval.seeds=1 --eval.n_episodes="$EPISODES" \
      --output_dir="$OUT/eval/$(name "$run")/$step" --progress=false
  done &
done
wait

python docs/learning-curve/learning_curve.py --out="$OUT" --csv_dir="$CSV_DIR" --suffix="$SUFFIX" $RUNS
