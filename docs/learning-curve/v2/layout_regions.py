"""Where on the table a policy fails: held-out success by where the target object starts.

    python docs/learning-curve/v2/layout_regions.py --arm=12k=outputs/levers6/eval/PickPlaceFixedBin-v0_standard_dart06_12k_s*/01[012]000

Each --arm is NAME=GLOB of sweep folders (their results.parquet); every rollout of an arm is placed by the
target object's starting bearing from the arm's base, recomputed from its seed (the sweep stores where
objects end). Task 1's fixed bowl stands at -50 degrees and no object starts next to it, so its
layouts fall into two regions: `side`, beyond the bowl (bearing below --side degrees, up to the -95 degree
edge), and `front`, everything else. Rollouts of one layout are not independent (the same layout in every
checkpoint), so the interval of the difference is a bootstrap over layouts.
"""

from __future__ import annotations

import argparse
import glob
import math
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from lerobot_condground.envs.pickplace_env import PickPlaceEnv
from lerobot_condground.evaluation.results import read_table


def start_bearing(envs: dict[str, PickPlaceEnv], task: str, seed: int) -> float:
    """The layout the sweep's rollout of this seed ran in: the env draws it from its reset seed."""
    if task not in envs:
        envs[task] = PickPlaceEnv(task=task, condition="clean", observation_height=96, observation_width=128)
    envs[task].reset(seed=seed)
    x, y = envs[task].layout.target_object.xy
    return math.degrees(math.atan2(y, x))


def bootstrap_difference(per_layout: pd.DataFrame, seed: int = 0) -> tuple[float, float]:
    """95 % percentile interval of front minus side success, resampling layouts within each region."""
    front, side = (per_layout.loc[per_layout.region == r, "success"].to_numpy() for r in ("front", "side"))
    result = stats.bootstrap(
        (front, side), lambda a, b, axis: a.mean(axis) - b.mean(axis), method="percentile", rng=seed
    )
    return result.confidence_interval.low, result.confidence_interval.high


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--arm", action="append", required=True, help="NAME=GLOB of sweep folders")
    parser.add_argument("--side", type=float, default=-65.0, help="bearing (degrees) below which is `side`")
    parser.add_argument("--csv", type=Path, help="also write every arm's table here")
    args = parser.parse_args()
    bearings: dict[tuple[str, int], float] = {}
    envs: dict[str, PickPlaceEnv] = {}
    tables = []
    for spec in args.arm:
        name, _, pattern = spec.partition("=")
        folders = sorted(glob.glob(pattern))
        if not folders:
            raise SystemExit(f"--arm={spec!r}: no folder matches")
        rows = pd.concat([read_table(f"{folder}/results.parquet") for folder in folders])
        rows = rows[rows.condition == "clean"]
        for key in {(t, int(s)) for t, s in zip(rows.task, rows.layout_seed, strict=True)} - set(bearings):
            bearings[key] = start_bearing(envs, *key)
        rows["bearing"] = [bearings[(t, int(s))] for t, s in zip(rows.task, rows.layout_seed, strict=True)]
        rows["region"] = np.where(rows.bearing < args.side, "side", "front")
        table = rows.groupby("region").agg(
            layouts=("layout_seed", "nunique"), rollouts=("success", "size"), success=("success", "mean"),
            pick=("pick", "mean"), lift=("lift", "mean"),
        )  # fmt: skip
        per_layout = rows.groupby(["region", "layout_seed"], as_index=False)["success"].mean()
        table["layouts_never"] = per_layout[per_layout.success == 0].groupby("region").size()
        table = table.fillna({"layouts_never": 0}).astype({"layouts_never": int})
        low, high = bootstrap_difference(per_layout)
        diff = table.loc["front", "success"] - table.loc["side", "success"]
        print(f"{name}: {len(folders)} sweeps")
        print(table.to_string(float_format=lambda v: f"{v:.3f}"))
        print(f"front - side: {diff:+.3f} [{low:+.3f}, {high:+.3f}] (bootstrap over layouts)\n")
        tables.append(
            table.reset_index().assign(arm=name, front_minus_side=diff, diff_low=low, diff_high=high)
        )
    if args.csv:
        table = pd.concat(tables)
        first = ["arm", "region"]
        table[first + [c for c in table.columns if c not in first]].to_csv(
            args.csv, index=False, float_format="%.4f"
        )


if __name__ == "__main__":
    main()
