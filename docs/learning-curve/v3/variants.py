"""A variant at the CPU configuration with every training seed it has, by the protocol: the sweeps `condground
compare` wrote (or the same `condground sweep` commands, of one checkpoint or several) anywhere under
<eval>/<task>_standard_<arm>_s<seed>/ (compare names its runs after `--train.variant`, standard, whatever an arm's
flags set), for each --eval given; a checkpoint's step is read off its path.

    python docs/learning-curve/v3/variants.py --eval=outputs/compare30/eval --seeds=0,1
    python docs/learning-curve/v3/variants.py --task=PickPlaceRandomBin-v0 --arm=bf16_cl \
        --eval=outputs/compare33/eval --eval=outputs/compare33/full_mixed
    python docs/learning-curve/v3/variants.py --variant=full --arm=full_detach --eval=outputs/compare32/eval

Merges the arm's rollouts, checkpoints and stage funnel into levers_rollouts.csv, levers_checkpoints.csv and
levers_funnel.csv (in place of its earlier rows: a later `condground compare --baseline.rollouts=...` then pairs
a treated arm's seeds with these), and writes the variant's rows of variants.csv: one per condition, the last
three checkpoints of every seed pooled, Wilson's interval of the pooled rollouts (which treats them as
independent: narrower than the runs' spread allows), and each seed's rate.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from lerobot_condground.evaluation.results import read_table
from lerobot_condground.evaluation.statistics import METRICS, cell_metrics, rate
from lerobot_condground.experiments.compare import merge_csv

HERE = Path(__file__).parent
VARIANTS = ("standard", "augmentation", "augmentation_attention", "full")
VARIANT_COLUMNS = [
    "task",
    "variant",
    "condition",
    "success",
    "n",
    "ci_low",
    "ci_high",
    "seeds",
    "seed_success",
    "source",
]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--eval", type=Path, action="append", required=True)
    parser.add_argument("--task", default="PickPlaceFixedBin-v0")
    parser.add_argument("--variant", default="standard", choices=VARIANTS)
    parser.add_argument("--arm", default="actsize_6k")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--steps", default="4000,5000,6000")
    parser.add_argument("--conditions", default="clean,full_mixed")
    args = parser.parse_args()
    seeds, steps = [int(s) for s in args.seeds.split(",")], [int(s) for s in args.steps.split(",")]
    conditions = args.conditions.split(",")
    frames = []
    for seed in seeds:
        run = f"{args.task}_standard_{args.arm}_s{seed}"
        for path in (p for root in args.eval for p in sorted((root / run).glob("**/results.parquet"))):
            table = read_table(path)
            step = table["checkpoint"].str.extract(r"(\d+)/pretrained_model$")[0].astype(int)
            frames.append(table.assign(seed=seed, step=step))
    every = pd.concat(frames, ignore_index=True)
    every = every[every["condition"].isin(conditions) & every["step"].isin(steps)]
    counts = every.groupby(["seed", "step", "condition"]).size()
    expected = pd.MultiIndex.from_product([seeds, steps, conditions], names=counts.index.names)
    if not counts.reindex(expected).eq(counts.max()).all():
        raise SystemExit(f"every seed, step and condition needs the same held-out sweep; found\n{counts}")
    every = every.assign(lever=args.arm, task=args.task)
    every["success"] = every["success"].astype(int)

    checkpoints = []
    for (condition, seed, step), f in every.groupby(["condition", "seed", "step"]):
        r = rate(int(f["success"].sum()), len(f))
        checkpoints.append(
            {"lever": args.arm, "task": args.task, "condition": condition, "seed": seed, "step": step,
             "success": r["rate"], "n": r["n"], "ci_low": r["low"], "ci_high": r["high"]}
        )  # fmt: skip
    merge_csv(HERE / "levers_checkpoints.csv", pd.DataFrame(checkpoints), [args.arm])
    merge_csv(
        HERE / "levers_rollouts.csv",
        every[["lever", "task", "condition", "seed", "step", "layout_seed", "success"]],
        [args.arm],
    )
    funnel = cell_metrics(every, by=("lever", "task", "condition"))
    funnel = funnel[
        ["lever", "task", "condition", "episodes", *(f"{m}{s}" for m in METRICS for s in ("", "_k", "_n"))]
    ]
    merge_csv(HERE / "levers_funnel.csv", funnel, [args.arm])

    rows = []
    for condition, f in every.groupby("condition"):
        r = rate(int(f["success"].sum()), len(f))
        by_seed = f.groupby("seed")["success"].mean()
        rows.append(
            {"task": args.task, "variant": args.variant, "condition": condition, "success": r["rate"], "n": r["n"],
             "ci_low": r["low"], "ci_high": r["high"], "seeds": len(by_seed),
             "seed_success": " ".join(f"{v:.4f}" for v in by_seed), "source": f"levers_rollouts.csv:{args.arm}"}
        )  # fmt: skip
    table = merge_csv(
        HERE / "variants.csv", pd.DataFrame(rows, columns=VARIANT_COLUMNS), [args.variant], column="variant"
    )
    print(pd.DataFrame(checkpoints).to_string(index=False))
    print(table.to_string(index=False))


if __name__ == "__main__":
    main()
