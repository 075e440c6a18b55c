"""One competitor at a time: the 6000-step checkpoints of each arm's runs under single-competitor conditions,
from the sweeps `condground sweep --sweep.conditions=object_neither_1,object_color_1,receptacle_neither_1`
wrote under <out>/roles/<run>/ (50 held-out layouts a condition).

    python docs/learning-curve/v3/roles.py --out=outputs/levers28 --arms=actsize_6k,augmentation --seeds=0,1

Writes roles_6000.csv (per arm, seed and condition: success, pick, grasped nothing, competitor object and
receptacle chosen; rows of runs and conditions not swept here are kept) and, where both arms have two seeds or
more, roles_6000_diff.csv (second arm less the first per condition, paired by layout with the training run as
the replicate: `statistics.clustered_difference`). A run without sweeps under <out> is skipped.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from lerobot_condground.evaluation.results import read_table
from lerobot_condground.evaluation.statistics import clustered_difference

HERE = Path(__file__).parent
TASK = "PickPlaceFixedBin-v0"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--arms", default="actsize_6k,augmentation", help="baseline first")
    parser.add_argument("--seeds", default="0,1")
    args = parser.parse_args()
    arms, seeds = args.arms.split(","), [int(s) for s in args.seeds.split(",")]
    rows, frames = [], []
    for arm in arms:
        for seed in seeds:
            path = args.out / "roles" / f"{TASK}_standard_{arm}_s{seed}" / "results.parquet"
            if not path.exists():
                print(f"no sweeps of {arm}, seed {seed}: {path}")
                continue
            table = read_table(path)
            frames.append(table.assign(arm=arm, run=seed))
            for condition, f in table.groupby("condition"):
                rows.append(
                    {"arm": arm, "seed": seed, "step": 6000, "condition": condition, "n": len(f),
                     "success": f["success"].mean(), "pick": f["pick"].mean(),
                     "grasped_nothing": (f["grasped_first"] == 0).mean(),
                     "competitor_object": f["selected_competitor_object"].mean(),
                     "competitor_receptacle": f["placed_in_competitor_receptacle"].mean()}
                )  # fmt: skip
    keys = ["arm", "seed", "step", "condition"]
    new = pd.DataFrame(rows)
    published = HERE / "roles_6000.csv"
    if published.exists():
        kept = pd.read_csv(published)
        kept = kept[~kept.set_index(keys).index.isin(new.set_index(keys).index)]
        new = pd.concat([kept, new], ignore_index=True)
    new.sort_values(keys).to_csv(published, index=False, float_format="%.4f")
    every = pd.concat(frames, ignore_index=True).rename(columns={"layout_seed": "layout"})
    every["success"] = every["success"].astype(float)
    diffs = []
    for condition, f in every.groupby("condition"):
        base, treated = (f[f["arm"].eq(arm)][["run", "layout", "success"]] for arm in arms[:2])
        if min(base["run"].nunique(), treated["run"].nunique()) < 2:
            continue
        c = clustered_difference(base, treated)
        diffs.append(
            {"condition": condition, "baseline_arm": arms[0], "treated_arm": arms[1], "seeds": len(seeds),
             "layouts": c["layouts"], "baseline": c["rate_a"], "treated": c["rate_b"], "diff": c["diff"],
             "low": c["low"], "high": c["high"], "p": c["p_value"],
             "seed_effects": " ".join(f"{e:+.4f}" for e in c["seed_effects"])}
        )  # fmt: skip
    print(new.to_string(index=False))
    if not diffs:
        return
    table = pd.DataFrame(diffs)
    table.to_csv(HERE / "roles_6000_diff.csv", index=False, float_format="%.4f")
    print(table.to_string(index=False))


if __name__ == "__main__":
    main()
