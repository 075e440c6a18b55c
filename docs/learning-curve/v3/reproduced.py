"""Did a `condground compare` run from flags reproduce a published comparison? Rollout by rollout: every pooled
rollout of the run's folder against the same (arm, condition, seed, step, layout) in a published
`levers_rollouts.csv`, and its summary against the published `levers.csv` rows.

    python docs/learning-curve/v3/reproduced.py \\
        --comparison=outputs/compare30/comparisons/PickPlaceFixedBin-v0_augmentation_vs_actsize_6k

Writes reproduced.csv beside this file: per arm, condition, seed and step, the published and the rerun success
and how many of the paired rollouts agree.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

HERE = Path(__file__).parent
KEY = ["lever", "condition", "seed", "step", "layout_seed"]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--comparison", type=Path, required=True)
    parser.add_argument("--published", type=Path, default=HERE / "levers.csv")
    args = parser.parse_args()
    rerun = pd.read_parquet(args.comparison / "rollouts.parquet")
    rerun = rerun.rename(columns={"arm": "lever"}).assign(success=lambda f: f["success"].astype(int))
    published = pd.read_csv(args.published.with_name(f"{args.published.stem}_rollouts.csv"))
    task = rerun["task"].iloc[0] if "task" in rerun else published["task"].iloc[0]
    published = published[published["task"].eq(task) & published["lever"].isin(rerun["lever"].unique())]
    both = published.merge(rerun[KEY + ["success"]], on=KEY, how="outer", suffixes=("_published", "_rerun"))
    missing = both["success_published"].isna() | both["success_rerun"].isna()
    if missing.any():
        raise SystemExit(f"{int(missing.sum())} rollouts are in one table only:\n{both[missing].head()}")
    both["agree"] = both["success_published"].eq(both["success_rerun"])
    table = (
        both.groupby(["lever", "condition", "seed", "step"])
        .agg(
            n=("agree", "size"),
            published=("success_published", "mean"),
            rerun=("success_rerun", "mean"),
            agree=("agree", "sum"),
        )
        .reset_index()
    )
    table.to_csv(HERE / "reproduced.csv", index=False, float_format="%.4f")
    print(table.to_string(index=False))
    summary = pd.read_csv(args.comparison / "summary.csv")
    rows = pd.read_csv(args.published)
    rows = rows[rows["task"].eq(task) & rows["lever"].isin(summary["lever"])]
    columns = ["lever", "condition", "baseline", "treated", "diff", "diff_low", "diff_high", "p"]
    print(rows[columns].merge(summary[columns], on=["lever", "condition"], suffixes=("", "_rerun")).T)
    print(f"{int(both['agree'].sum())} of {len(both)} rollouts agree")


if __name__ == "__main__":
    main()
