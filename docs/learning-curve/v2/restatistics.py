"""The lever table again with the run-aware, layout-paired statistics (issue 57): adds `cluster_low`,
`cluster_high`, `cluster_p`, `holm_p` and `cluster_source` to levers.csv, from what survives of each arm.

    python docs/learning-curve/v2/restatistics.py

`cluster_source` says where each row's figures come from:
- `rollouts`: both arms' per-rollout outcomes (`levers_rollouts.csv`): `statistics.clustered_difference`;
- `checkpoints`: only the checkpoint rates survive (`levers_checkpoints.csv`, the earlier sessions'
  levers): the run rates are exact, the layout part is bounded by p_a(1 − p_a) + p_b(1 − p_b) over the 50
  layouts, which holds when a layout hard for one arm is not easier for the other (non-negative
  correlation of the arms' layout rates); wider than the paired figure would be.
`holm_p` is Holm's adjustment over every row of the table (one family: the levers ever tried).
The columns already in the table (Newcombe's interval, McNemar's p) are left as published.
"""

from pathlib import Path

import numpy as np
import pandas as pd

from lerobot_condground.evaluation.statistics import clustered_difference, holm, run_layout_interval

HERE = Path(__file__).parent
LAYOUTS = 50


def arm_rollouts(rollouts: pd.DataFrame, arm: str, task: str) -> pd.DataFrame | None:
    rows = rollouts[(rollouts.lever == arm) & (rollouts.task == task)]
    if rows.empty:
        return None
    return rows.rename(columns={"seed": "run", "layout_seed": "layout"})


def arm_run_rates(checkpoints: pd.DataFrame, arm: str, task: str) -> pd.Series:
    rows = checkpoints[(checkpoints.lever == arm) & (checkpoints.task == task)]
    if rows.empty:
        raise SystemExit(f"{arm} on {task}: neither rollouts nor checkpoint rates in the published tables")
    last = rows.groupby("seed").step.transform(lambda s: s >= sorted(s.unique())[-3])
    return rows[last].groupby("seed").success.mean()


def restate(row, rollouts: pd.DataFrame, checkpoints: pd.DataFrame) -> dict:
    a = arm_rollouts(rollouts, row.baseline_arm, row.task)
    b = arm_rollouts(rollouts, row.lever, row.task)
    if a is not None and b is not None:
        d, source = clustered_difference(a, b), "rollouts"
    else:
        ra = arm_run_rates(checkpoints, row.baseline_arm, row.task)
        rb = arm_run_rates(checkpoints, row.lever, row.task)
        pa, pb = ra.mean(), rb.mean()
        d, source = run_layout_interval(ra, rb, pa * (1 - pa) + pb * (1 - pb), LAYOUTS), "checkpoints"
    return {
        "cluster_low": d["low"],
        "cluster_high": d["high"],
        "cluster_p": d["p_value"],
        "cluster_source": source,
    }


def main() -> None:
    table = pd.read_csv(HERE / "levers.csv")
    rollouts = pd.read_csv(HERE / "levers_rollouts.csv")
    checkpoints = pd.read_csv(HERE / "levers_checkpoints.csv")
    table = table.drop(
        columns=[
            c for c in ("cluster_low", "cluster_high", "cluster_p", "holm_p", "cluster_source") if c in table
        ]
    )
    new = pd.DataFrame([restate(row, rollouts, checkpoints) for row in table.itertuples()], index=table.index)
    table = pd.concat([table, new], axis=1)
    table.insert(table.columns.get_loc("cluster_source"), "holm_p", holm(table.cluster_p))
    table.to_csv(HERE / "levers.csv", index=False, float_format="%.4f")
    held = (table.p < 0.05) & ~(table.holm_p < 0.05)
    for row in table[held].itertuples():
        print(
            f"{row.lever} ({row.task}, against {row.baseline_arm}): p {row.p:.4f} -> cluster p {row.cluster_p:.4f}, Holm {row.holm_p:.4f}"
        )
    print(
        f"{int((table.p < 0.05).sum())} rows at p < 0.05 before, {int((table.holm_p < 0.05).sum())} after ({np.isnan(table.cluster_p).sum()} without an interval)"
    )


if __name__ == "__main__":
    main()
