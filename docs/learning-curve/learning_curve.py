"""Learning-curve CSVs and plots from the runs of docs/learning-curve/learning_curve.sh.

    python docs/learning-curve/learning_curve.py --out=outputs/learning-curve --csv_dir=docs/learning-curve TASK:VARIANT ...

Per run: <task>_<variant>[_<flags>].csv (minutes,steps,samples,success,n,ci_low,ci_high), the training loss
as <...>_loss.csv, and one plot per task (<task>.png): clean success against wall-clock minutes, and loss.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import matplotlib
import pandas as pd

from lerobot_condground.evaluation.results import read_table
from lerobot_condground.evaluation.statistics import cell_metrics

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def run_name(run: str) -> str:
    """As learning_curve.sh names a run: TASK:VARIANT[:FLAGS]@NAME -> TASK_VARIANT_NAME, else the spec."""
    if "@" in run:
        spec, name = run.split("@", 1)
        run = "_".join([*spec.split(":")[:2], name])
    return re.sub(r"[:,=./]", "_", run)


def training_minutes(segments: list[list[float]], t: float) -> float:
    """Wall-clock minutes of training up to time t, over the run's "start stop" segments (resumes)."""
    done = 0.0
    for segment in segments:
        if len(segment) == 2 and t > segment[1]:
            done += segment[1] - segment[0]
        else:
            return (done + t - segment[0]) / 60
    raise ValueError(f"time {t} is after every training segment {segments}")


def losses(out: Path, name: str, log_freq: int) -> pd.DataFrame:
    # The first segment's log, then one per resume named by the step it went on from; lerobot-train logs
    # the step rounded (1K, 2K, ...), a logged line every log_freq steps.
    logs = {0: out / "train" / f"{name}.log"}
    for log in (out / "train").glob(f"{name}.resume-*.log"):
        logs[int(log.stem.rsplit("-", 1)[1])] = log
    firsts = sorted(logs)
    rows = []
    for first, until in zip(firsts, [*firsts[1:], float("inf")], strict=True):
        values = [float(v) for v in re.findall(r"step:\S+ .*?l1_loss:([0-9.]+)", logs[first].read_text())]
        rows += [
            (first + log_freq * (i + 1), v)
            for i, v in enumerate(values)
            if first + log_freq * (i + 1) <= until
        ]
    return pd.DataFrame(rows, columns=["steps", "l1_loss"])


def curve(out: Path, run: str) -> tuple[pd.DataFrame, pd.DataFrame]:
    name = run_name(run)
    train = out / "train" / name
    segments = [
        [float(v) for v in line.split()]
        for line in (out / "train" / f"{name}.start").read_text().splitlines()
    ]
    train_config = json.loads(
        next(train.glob("checkpoints/*/pretrained_model/train_config.json")).read_text()
    )
    batch, log_freq = train_config["batch_size"], train_config["log_freq"]
    rows = []
    for results in sorted((out / "eval" / name).glob("*/results.parquet")):
        saved = (train / "checkpoints" / results.parent.name / "pretrained_model").stat().st_mtime
        metrics = cell_metrics(read_table(results)).iloc[0]
        step = int(results.parent.name)
        rows.append(
            {
                "minutes": round(training_minutes(segments, saved), 1),
                "steps": step,
                "samples": step * batch,
                "success": metrics["success"],
                "n": int(metrics["success_n"]),
                "ci_low": metrics["success_low"],
                "ci_high": metrics["success_high"],
                "p_pick": metrics["p_pick"],
            }
        )
    return pd.DataFrame(rows).sort_values("steps"), losses(out, name, log_freq)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--csv_dir", type=Path, required=True)
    parser.add_argument(
        "--suffix", default="", help="run-name suffix (learning_curve.sh: _demos<DEMOS>, _<H>x<W>)"
    )
    parser.add_argument("runs", nargs="+", help="TASK:VARIANT[:FLAG,...] as given to learning_curve.sh")
    args = parser.parse_args()
    args.csv_dir.mkdir(parents=True, exist_ok=True)
    by_task: dict[str, list[str]] = {}
    for run in args.runs:
        by_task.setdefault(run.split(":")[0], []).append(run)
    for task, runs in by_task.items():
        fig, (ax_loss, ax_success) = plt.subplots(1, 2, figsize=(10, 3.6))
        for run in runs:
            success, loss = curve(args.out, run + args.suffix)
            stem = run_name(run + args.suffix)
            success.to_csv(args.csv_dir / f"{stem}.csv", index=False, float_format="%.4f")
            loss.to_csv(args.csv_dir / f"{stem}_loss.csv", index=False)
            print(run, "\n", success.to_string(index=False))
            label = run_name(run + args.suffix).removeprefix(f"{task}_")
            ax_loss.plot(loss.steps, loss.l1_loss, label=label)
            ax_success.errorbar(
                success.minutes,
                100 * success.success,
                yerr=[100 * (success.success - success.ci_low), 100 * (success.ci_high - success.success)],
                fmt="o-",
                capsize=3,
                label=label,
            )
        ax_loss.set(xlabel="training steps", ylabel="training L1 loss (normalized actions)", yscale="log")
        ax_success.set(
            xlabel="wall-clock minutes of training (one core per run)",
            ylabel="clean success, % (95 % CI)",
            ylim=(-5, 105),
        )
        for ax in (ax_loss, ax_success):
            ax.grid(alpha=0.3)
            ax.legend()
        fig.suptitle(f"act_modified from scratch on a 2-core CPU, {task}")
        fig.tight_layout()
        fig.savefig(args.csv_dir / f"{task}{args.suffix}.png", dpi=110)


if __name__ == "__main__":
    main()
