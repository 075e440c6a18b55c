"""The learning-curve set of a device run (docs/learning-curve/gpu/device_curve.sh) from the results it brought back.

    mkdir -p outputs/device && tar xzf "$FILES_AT/results.tgz" -C outputs/device   # FILES_AT: the call's files_at
    python docs/learning-curve/gpu/device_curve.py --results=outputs/device --batch=32 --csv_dir=docs/learning-curve/gpu

Writes `<csv_dir>/<task>_<variant>.csv` (minutes,steps,samples,success,n,ci_low,ci_high,seed: minutes of
training from the run's progress bars, every swept checkpoint) and `<csv_dir>/rollouts.csv` (each rollout's
layout and stages). A sweep stopped at its deadline counts the parts it finished, so `n` can be below the
rollouts asked for.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd

from lerobot_condground.evaluation.results import read_table
from lerobot_condground.evaluation.statistics import rate

RUN = re.compile(r"(?P<task>.+-v\d+)_(?P<variant>[a-z_]+)_s(?P<seed>\d+)")


def elapsed_minutes(log: Path, step: int, total: int | None = None) -> float:
    """Wall-clock minutes of training at `step`, from the progress bars `condground train` logs. A resumed
    run's bar counts the steps left from 0; the minutes add up over the segments, each counted up to the
    checkpoint the next one resumed from (steps past it were lost with the run that made them). At GPU rates
    tqdm skips steps: the last line at or before the step counts. `total` defaults to the first bar's length
    (right for a run never resumed)."""
    elapsed: dict[int, dict[int, float]] = {}  # steps left at the segment's start -> {step in it: minutes}
    for done, left, clock in re.findall(
        r" (\d+)/(\d+) \[(\d+(?::\d+){1,2})<", log.read_text(errors="replace")
    ):
        seconds = sum(int(v) * 60**i for i, v in enumerate(reversed(clock.split(":"))))
        elapsed.setdefault(int(left), {}).setdefault(int(done), seconds / 60)
    total = total or max(elapsed, default=0)
    starts = sorted(total - left for left in elapsed)  # the step each segment started from
    minutes = 0.0
    for i, start in enumerate(starts):
        stop = starts[i + 1] if i + 1 < len(starts) else total
        lines, upto = elapsed[total - start], min(step, stop) - start
        before = [done for done in lines if done <= upto]
        if not before or max(lines) < upto:
            raise SystemExit(f"{log}: the run from step {start} has no progress line at step {upto + start}")
        minutes += lines[max(before)]
        if step <= stop:
            return minutes
    raise SystemExit(f"{log}: step {step} is past the run's {total} steps")


def outcomes(step_dir: Path) -> pd.DataFrame:
    whole = step_dir / "results.parquet"
    parts = sorted(step_dir.glob("parts/*/*/*.parquet")) if not whole.exists() else [whole]
    return pd.concat([read_table(p) for p in parts]) if parts else pd.DataFrame()


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--results", type=Path, required=True, help="the unpacked results.tgz")
    parser.add_argument("--batch", type=int, required=True, help="the runs' --batch_size")
    parser.add_argument("--csv_dir", type=Path, required=True)
    args = parser.parse_args()
    if not (args.results / "eval").is_dir():
        raise SystemExit(
            f"--results={args.results}: no eval/ folder; pass the folder results.tgz was unpacked into"
        )
    curves, rollouts = {}, []
    for run in sorted((args.results / "eval").iterdir()):
        match = RUN.fullmatch(run.name)
        if not match:
            raise SystemExit(f"{run}: not a <task>_<variant>_s<seed> run folder")
        log = args.results / "train" / f"{run.name}.log"
        for step_dir in sorted(run.iterdir()):
            frame = outcomes(step_dir)
            if frame.empty:
                continue
            step = int(step_dir.name)
            r = rate(int(frame["success"].sum()), len(frame))
            curves.setdefault((match["task"], match["variant"]), []).append(
                {"minutes": round(elapsed_minutes(log, step), 2), "steps": step,
                 "samples": step * args.batch, "success": r["rate"], "n": r["n"], "ci_low": r["low"],
                 "ci_high": r["high"], "seed": int(match["seed"])}
            )  # fmt: skip
            keep = ["layout_seed", "success", "pick", "lift", "place"]
            rollouts.append(frame[keep].assign(task=match["task"], variant=match["variant"], step=step))
    if not curves:
        raise SystemExit(f"{args.results}: no swept checkpoint")
    args.csv_dir.mkdir(parents=True, exist_ok=True)
    figure, axis = plt.subplots(figsize=(6, 3.5))
    for (task, variant), rows in curves.items():
        table = pd.DataFrame(rows)
        table.to_csv(args.csv_dir / f"{task}_{variant}.csv", index=False, float_format="%.4f")
        print(f"{task} {variant}\n{table.to_string(index=False)}")
        error = [100 * (table.success - table.ci_low), 100 * (table.ci_high - table.success)]
        axis.errorbar(
            table.minutes, 100 * table.success, yerr=error, marker="o", capsize=3, label=f"{task} {variant}"
        )
    axis.set(
        xlabel="minutes of training on the GPU", ylabel="clean success, held-out layouts (%)", ylim=(0, 100)
    )
    axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(args.csv_dir / "curves.png", dpi=120)
    columns = ["task", "variant", "step", "layout_seed", "success", "pick", "lift", "place"]
    pd.concat(rollouts)[columns].astype({"success": int, "pick": int, "lift": int, "place": int}).to_csv(
        args.csv_dir / "rollouts.csv", index=False
    )


if __name__ == "__main__":
    main()
