"""Two arms scored among the copy-paste pool's rendered competitors (issue 55: novel assets or clutter?).

`condground compare` scores under the protocol's scenes; this pairs sweeps of the same checkpoints under
`full_mixed` with `--env.competitor_pool=augmentation`, which `run` writes as <out>/pool/<run>/ (one sweep of
a run's pooled checkpoints on the protocol's 50 held-out layouts):

    python docs/learning-curve/v3/in_distribution.py run --out=outputs/compare32 --arms=bf16_cl,rendered_clutter
    python docs/learning-curve/v3/in_distribution.py analyse --out=outputs/compare32 --arms=bf16_cl,rendered_clutter

An arm trained elsewhere is named by its run folders (`--runs=ARM=RUN_S0,RUN_S1`, one a seed), and a baseline whose
pooled rollouts under this condition are already published is read from levers_rollouts.csv
(`--published=true`: the first arm is not swept again).

`analyse` adds the pair's row to levers.csv (condition `full_mixed (augmentation competitors)`, the protocol's
columns: Newcombe/McNemar over pooled rollouts and the layout-clustered, run-aware interval), the rollouts to
levers_rollouts.csv and the stage funnel to levers_funnel.csv (in place of earlier rows of the arms there).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pandas as pd

from lerobot_condground.evaluation.results import read_table
from lerobot_condground.evaluation.statistics import (
    METRICS,
    cell_metrics,
    clustered_difference,
    holm,
    paired_difference,
)
from lerobot_condground.experiments.compare import merge_csv, published_rollouts

HERE = Path(__file__).parent
CONDITION = "full_mixed"
LABEL = "full_mixed (augmentation competitors)"
STEPS = (4000, 5000, 6000)
LAYOUTS, OFFSET = 50, 1_000_000


def run_dir(args, arm: str, seed: int) -> Path:
    if arm in args.runs:
        return args.runs[arm][args.seeds.index(seed)]
    return args.out / "train" / f"{args.task}_standard_{arm}_s{seed}"


def swept(args) -> list[str]:
    return args.arms[1:] if args.published else args.arms


def sweep(args) -> None:
    for arm in swept(args):
        for seed in args.seeds:
            run = run_dir(args, arm, seed)
            paths = [run / "checkpoints" / f"{s:06d}" / "pretrained_model" for s in STEPS]
            command = [
                str(Path(sys.executable).parent / "condground"), "sweep",
                f"--policy.paths={','.join(map(str, paths))}", f"--env.task={args.task}", "--env.servo=interpolated",
                "--env.competitor_pool=augmentation", f"--sweep.conditions={CONDITION}", "--eval.seeds=1",
                f"--eval.n_episodes={LAYOUTS}", f"--eval.seed_offset={OFFSET}", f"--workers={args.workers}",
                f"--output_dir={args.out / 'pool' / run.name}", "--progress=false",
            ]  # fmt: skip
            print(" ".join(command), flush=True)
            subprocess.run(command, check=True)


def rollouts(args) -> pd.DataFrame:
    frames = []
    if args.published:
        table = published_rollouts(HERE / "levers_rollouts.csv", args.arms[0], args.task).query(
            "condition == @LABEL and seed in @args.seeds"
        )
        frames.append(table.assign(arm=table["lever"], run=table["seed"].map(args.seeds.index)))
    for arm in swept(args):
        for index, seed in enumerate(args.seeds):
            run = run_dir(args, arm, seed)
            table = read_table(args.out / "pool" / run.name / "results.parquet")
            step = table["checkpoint"].str.extract(r"/(\d{6})/pretrained_model")[0].astype(int)
            frames.append(table.assign(arm=arm, run=index, seed=seed, step=step))
    every = pd.concat(frames, ignore_index=True)
    counts = every.groupby(["arm", "seed", "step"]).size()
    if set(counts) != {LAYOUTS} or len(counts) != len(args.arms) * len(args.seeds) * len(STEPS):
        raise ValueError(f"expected {LAYOUTS} rollouts per arm, seed and checkpoint {STEPS}; got\n{counts}")
    return every.sort_values(["arm", "run", "step", "layout_seed"], ignore_index=True)


def analyse(args) -> None:
    every = rollouts(args)
    base, treated = (every[every["arm"].eq(a)] for a in args.arms)
    d = paired_difference(base["success"].to_numpy(), treated["success"].to_numpy())
    c = clustered_difference(
        *(
            f[["run", "layout_seed", "success"]].rename(columns={"layout_seed": "layout"})
            for f in (base, treated)
        )
    )
    row = {
        "lever": args.arms[1], "task": args.task, "condition": LABEL, "baseline_arm": args.arms[0],
        "seeds": len(args.seeds), "n": d["n"], "baseline": d["rate_a"], "treated": d["rate_b"], "diff": d["diff"],
        "diff_low": d["low"], "diff_high": d["high"], "p": d["p_value"], "cluster_low": c["low"],
        "cluster_high": c["high"], "cluster_p": c["p_value"],
        "seed_effects": " ".join(f"{e:+.4f}" for e in c["seed_effects"]),
        "steps": max(STEPS), "checkpoints": " ".join(map(str, STEPS)),
    }  # fmt: skip
    flags = pd.read_csv(HERE / "levers.csv", dtype=str).query("lever == @row['lever'] and task == @args.task")
    row["flags"] = flags["flags"].iloc[0] if len(flags) else ""
    levers = merge_csv(HERE / "levers.csv", pd.DataFrame([row]), [row["lever"]], baseline=args.arms[0])
    levers.assign(holm_p=holm(levers["cluster_p"])).to_csv(
        HERE / "levers.csv", index=False, float_format="%.4f"
    )
    # A published baseline's rows stay as they are: it may have been published with more seeds than this pair's.
    table = every[every["arm"].isin(swept(args))].assign(
        lever=lambda t: t["arm"], condition=LABEL, task=args.task
    )
    rollout_columns = ["lever", "task", "condition", "seed", "step", "layout_seed", "success"]
    merge_csv(HERE / "levers_rollouts.csv", table[rollout_columns].astype({"success": int}), swept(args))
    funnel = cell_metrics(table, by=("lever", "task", "condition"))
    funnel = funnel[
        ["lever", "task", "condition", "episodes", *(f"{m}{s}" for m in METRICS for s in ("", "_k", "_n"))]
    ]
    merge_csv(HERE / "levers_funnel.csv", funnel, swept(args))

    per = (
        every.assign(lever=every["arm"]).groupby(["lever", "seed", "step"])["success"].mean().unstack("step")
    )
    print(per.to_string(float_format=lambda v: f"{100 * v:.0f} %"))
    print(pd.DataFrame([row]).drop(columns=["flags"]).to_string(index=False))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("stage", choices=("run", "analyse"))
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument(
        "--arms", type=lambda s: s.split(","), default="bf16_cl,rendered_clutter", help="baseline first"
    )
    parser.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")], default="0,1")
    parser.add_argument("--task", default="PickPlaceFixedBin-v0")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(
        "--runs",
        type=lambda s: {k: [Path(p) for p in v.split(",")] for k, v in [s.split("=", 1)]},
        default={},
        help="ARM=RUN_S0,RUN_S1: an arm's run folders, one per seed",
    )
    parser.add_argument("--published", choices=("true", "false"), default="false")
    args = parser.parse_args()
    args.published = args.published == "true"
    (sweep if args.stage == "run" else analyse)(args)


if __name__ == "__main__":
    main()
