"""Learning curves against true one-core training minutes, from `condground compare` runs (issue 58).

    python docs/learning-curve/timed/timed.py --output_dir=outputs/compare32 --arm=bf16_cl --seeds=0,1 \
        --task=PickPlaceFixedBin-v0 --csv=docs/learning-curve/timed/PickPlaceFixedBin-v0_standard.csv

Per run `<output_dir>/train/<task>_standard_<arm>_s<seed>` and every checkpoint swept clean under
`<output_dir>/eval/<run>/<step>/` (compare's sweeps, plus the same `condground sweep` for the early
checkpoints): `minutes` from the training command's start (the line compare writes into the run's log; imports
and the frame cache's fill included) to the checkpoint's save, training only: recording and evaluation ran
apart. Refuses a run that resumed (its minutes would hold the pause).
Columns: v2's `minutes,steps,samples,success,n,ci_low,ci_high,seed`, then `samples_per_s` (LeRobot's logged
rate, median over the run) and the machine (`lscpu`'s model name, CPU family and model).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import re
import statistics
import subprocess
from pathlib import Path

import pandas as pd

from lerobot_condground.evaluation.results import read_table
from lerobot_condground.evaluation.statistics import cell_metrics

COLUMNS = [
    "minutes",
    "steps",
    "samples",
    "success",
    "n",
    "ci_low",
    "ci_high",
    "seed",
    "samples_per_s",
    "machine",
]
START = re.compile(r"^# (\d{4}-\d\d-\d\d \d\d:\d\d:\d\d) ", re.M)


def machine() -> str:
    fields = dict(
        line.split(":", 1) for line in subprocess.run(["lscpu"], capture_output=True, text=True).stdout.splitlines()
        if ":" in line
    )  # fmt: skip
    get = lambda key: fields.get(key, "?").strip()  # noqa: E731
    return f"{get('Model name')} (family {get('CPU family')}, model {get('Model')}), {get('CPU(s)')} cores"


def run_rows(output_dir: Path, task: str, arm: str, seed: int, condition: str) -> list[dict]:
    run = output_dir / "train" / f"{task}_standard_{arm}_s{seed}"
    log = run.with_suffix(".log").read_text()
    starts = START.findall(log)
    if len(starts) != 1:
        raise ValueError(
            f"{run}.log holds {len(starts)} training starts; allowed: one (a resumed run's minutes hold its pause)"
        )
    start = dt.datetime.strptime(starts[0], "%Y-%m-%d %H:%M:%S").timestamp()
    config = json.loads(next(run.glob("checkpoints/*/pretrained_model/train_config.json")).read_text())
    rates = [float(v) for v in re.findall(r" smp/s:([0-9.]+)", log)]
    rows = []
    for results in sorted((output_dir / "eval" / run.name).glob("*/results.parquet")):
        table = read_table(results)
        table = table[table["condition"].eq(condition)]
        if table.empty:
            continue
        step = int(results.parent.name)
        saved = (run / "checkpoints" / results.parent.name / "pretrained_model").stat().st_mtime
        metrics = cell_metrics(table).iloc[0]
        rows.append({
            "minutes": round((saved - start) / 60, 2), "steps": step, "samples": step * config["batch_size"],
            "success": metrics["success"], "n": int(metrics["success_n"]), "ci_low": metrics["success_low"],
            "ci_high": metrics["success_high"], "seed": seed, "samples_per_s": statistics.median(rates),
        })  # fmt: skip
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output_dir", type=Path, required=True)
    parser.add_argument("--task", required=True)
    parser.add_argument("--arm", required=True)
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--condition", default="clean")
    parser.add_argument("--csv", type=Path, required=True)
    args = parser.parse_args()
    rows = [
        row for seed in args.seeds.split(",")
        for row in run_rows(args.output_dir, args.task, args.arm, int(seed), args.condition)
    ]  # fmt: skip
    out = pd.DataFrame(rows, columns=COLUMNS).assign(machine=machine()).sort_values(["seed", "steps"])
    args.csv.parent.mkdir(parents=True, exist_ok=True)
    out.to_csv(args.csv, index=False, float_format="%.4f")
    print(out.drop(columns="machine").to_string(index=False))
    print(out["machine"].iloc[0])


if __name__ == "__main__":
    main()
