"""A training lever measured against the baseline as issue 27 asks: both trained side by side at the same
step budget, several training seeds each, the last checkpoints of every run pooled on the same held-out
layouts, paired layout by layout, with a 95 % interval and McNemar's exact p, and beside them the run-aware
interval (`statistics.clustered_difference`: the layout pairs, the training run replicates) and Holm's p over
the whole table, under each of --conditions (clean by default; `--conditions=clean,full_mixed` scores
look-alikes too, one row per condition).

    python examples/levers.py --task=PickPlaceFixedBin-v0 --data=outputs/levers/data/PickPlaceFixedBin-v0 \\
        --lever='cosine=--policy.scheduler_name=cosine' --seeds=0,1 --steps=12000 --every=2000 \\
        --out=outputs/levers --csv=docs/learning-curve/v2/levers.csv

Every run (baseline and each lever, each seed) trains with `condground train` on --threads torch threads,
all at once; the lever's flags come after the CPU configuration's (lerobot_condground/core/training.py), --data
and --flags, so a lever may train on another recording (`--lever='dart=--dataset.root=...'`). A rerun resumes
unfinished runs from their last checkpoint and skips finished evaluations. Pairs are (seed index, checkpoint
rank, layout): the k-th last checkpoint of the baseline's i-th seed against the k-th last of the lever's i-th
seed, on the same layout. A lever whose flags set `--steps` and `--save_freq` is a budget: its own last
checkpoints are pooled (`--lever='long=--steps=24000 --save_freq=2000'`). Writes one row per lever to --csv
(replacing an earlier row of the same lever and task), every checkpoint's rate beside it
(`<csv stem>_checkpoints.csv`) and every pooled rollout's outcome (`<csv stem>_rollouts.csv`, to re-pair
after outputs/ is gone) and each arm's stage funnel per condition (`<csv stem>_funnel.csv`), and prints
each arm's pooled rate; without --lever the baseline is measured alone.
With --published_baseline the baseline is not trained or evaluated: its pooled rollouts are read from
`<csv stem>_rollouts.csv` (an earlier session's runs of that name, on a recording made again from the same
seeds: recording is deterministic; tables without a `condition` column are clean rollouts).
With --heldout, `condground fit` of each run's last checkpoint on its first training demonstrations and on
the held-out recording (`<csv stem>_fit.csv`, per segment). With
--train_layouts=N, each run's last checkpoint also runs N rollouts on the recording's own layouts (its
seeds 0, 1, ...), and `--fit_vs_heldout_csv` gets its success there beside the held-out success. Last,
`condground failures` classifies each failed rollout of each run's last checkpoint on the held-out layouts
(`<csv stem>_failures.csv`: counts per cause, grasp offsets at closing, how a lifted target was lost).
With --curve=ARM:NAME, every checkpoint of that arm's runs on the held-out layouts: the learning curve
`<csv dir>/<task>_<NAME>.csv`.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd

from lerobot_condground.core.training import CPU_BATCH_SIZE, CPU_STEPS, policy_flags
from lerobot_condground.evaluation.results import read_table
from lerobot_condground.evaluation.statistics import (
    METRICS,
    cell_metrics,
    clustered_difference,
    holm,
    paired_difference,
    rate,
)


def parse_levers(specs: list[str], baseline: str) -> dict[str, list[str]]:
    """The baseline arm (no flags of its own) first, then each lever."""
    arms = {baseline: []}
    for spec in specs:
        name, sep, flags = spec.partition("=")
        if not sep or not name.isidentifier() or name in arms:
            raise SystemExit(f"--lever={spec!r}: expected NAME=FLAGS with a new identifier NAME")
        arms[name] = shlex.split(flags)
    return arms


def run_dir(args, arm: str, seed: int) -> Path:
    return args.out / "train" / f"{args.task}_{args.variant}_{arm}_s{seed}"


def checkpoint(train: Path, step: int) -> Path:
    return train / "checkpoints" / f"{step:06d}" / "pretrained_model"


def train_command(args, arm_flags: list[str], train: Path, seed: int) -> list[str]:
    last = train / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
    if last.exists():
        return ["condground", "train", f"--config_path={last}", "--resume=true"]
    return [
        "condground", "train", "--policy.type=act_modified", f"--policy.variant={args.variant}",
        "--policy.device=cpu", "--policy.push_to_hub=false", *policy_flags(), f"--batch_size={CPU_BATCH_SIZE}",
        f"--dataset.repo_id=local/{args.task}", f"--dataset.root={args.data}", f"--steps={args.steps}",
        f"--save_freq={args.every}", *args.flags, *arm_flags, "--log_freq=100", "--num_workers=0",
        "--wandb.enable=false", f"--seed={seed}", f"--output_dir={train}",
    ]  # fmt: skip


def train_all(args, arms: dict[str, list[str]]) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads), "MKL_NUM_THREADS": str(args.threads)}
    running = []
    for arm, flags in arms.items():
        for seed in args.seeds:
            train = run_dir(args, arm, seed)
            if checkpoint(train, args.budget[arm][0]).exists():
                continue
            train.parent.mkdir(parents=True, exist_ok=True)
            command = train_command(args, flags, train, seed)
            log = open(train.with_suffix(".log"), "a")  # noqa: SIM115 (closed when the run ends)
            log.write(f"\n# {time.strftime('%F %T')} {shlex.join(command)}\n")
            log.flush()
            running.append(
                (
                    train,
                    subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env),
                    log,
                    args.budget[arm][0],
                )
            )
    for train, process, log, steps in running:
        process.wait()
        log.close()
        if process.returncode or not checkpoint(train, steps).exists():
            raise SystemExit(f"training {train.name} failed (rc {process.returncode}); see {train}.log")


def budgets(args, arms: dict[str, list[str]]) -> dict[str, tuple[int, int]]:
    """(steps, checkpoint interval) of each arm: --steps and --every unless its flags set --steps or
    --save_freq (a lever may be the budget itself)."""
    parser = argparse.ArgumentParser(allow_abbrev=False)
    parser.add_argument("--steps", type=int, default=args.steps)
    parser.add_argument("--save_freq", type=int, default=args.every)
    out = {}
    for arm, flags in arms.items():
        budget = parser.parse_known_args(flags)[0]  # the last of repeated flags wins, as in draccus
        steps, every = budget.steps, budget.save_freq
        if steps % every:
            raise SystemExit(f"{arm}: --save_freq={every} does not divide --steps={steps}")
        last = steps - every * (args.pool - 1)
        if last <= 0:
            raise SystemExit(
                f"{arm}: --pool={args.pool} checkpoints every {every} steps do not fit in {steps}"
            )
        out[arm] = (steps, every)
    return out


def pooled_steps(args, arm: str) -> list[int]:
    steps, every = args.budget[arm]
    return list(range(steps - every * (args.pool - 1), steps + 1, every))


def evaluate_all(args, arms: dict[str, list[str]]) -> None:
    todo = []
    for arm in arms:
        for seed in args.seeds:
            for step in pooled_steps(args, arm):
                out = args.out / "eval" / f"{run_dir(args, arm, seed).name}" / f"{step:06d}"
                if not swept(out / "results.parquet", args.conditions):
                    todo.append((checkpoint(run_dir(args, arm, seed), step), out))
    # The last checkpoints again on the recording's own layouts (its seeds 0, 1, ...: fit or generalization?).
    for arm in arms if args.train_layouts else ():
        for seed in args.seeds:
            out = args.out / "eval_train" / run_dir(args, arm, seed).name / f"{args.budget[arm][0]:06d}"
            if not (out / "results.parquet").exists():
                todo.append((checkpoint(run_dir(args, arm, seed), args.budget[arm][0]), out))
    sweep_all(args, todo, args.conditions)


def swept(results: Path, conditions: list[str]) -> bool:
    """Whether a sweep's table holds every condition asked for (a sweep resumes, so a new condition is added)."""
    return results.exists() and set(conditions) <= set(read_table(results)["condition"])


def sweep_all(args, todo: list[tuple[Path, Path]], conditions: list[str]) -> None:
    """One sweep per (checkpoint, output folder), resumable one by one, --jobs at once on one worker each; the
    held-out layouts under `conditions`, the recording's own ones (eval_train) clean."""
    commands = []
    for ckpt, out in todo:
        own_layouts = out.parts[-3] == "eval_train"
        commands.append([
            "condground", "sweep", f"--policy.paths={ckpt}", f"--env.task={args.task}",
            f"--env.servo={args.servo}", f"--sweep.conditions={'clean' if own_layouts else ','.join(conditions)}",
            "--eval.seeds=1",
            f"--eval.n_episodes={args.train_layouts if own_layouts else args.episodes}",
            f"--eval.seed_offset={0 if own_layouts else args.seed_offset}", "--workers=1",
            f"--output_dir={out}", "--progress=false",
        ])  # fmt: skip
    run_all(commands, args.jobs)


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


def curves(args, arms: dict[str, list[str]]) -> None:
    """Every checkpoint of the --curve arms on the held-out layouts: `<csv dir>/<task>_<name>.csv`
    (minutes,steps,samples,success,n,ci_low,ci_high,seed) and a plot beside it."""
    named = dict(spec.split(":", 1) for spec in args.curve)
    unknown = set(named) - set(arms)
    if unknown:
        raise SystemExit(f"--curve names arms {sorted(unknown)}; arms: {sorted(arms)}")

    def steps(arm):
        total, every = args.budget[arm]
        return range(every, total + 1, every)

    todo = [
        (checkpoint(run_dir(args, arm, seed), step), args.out / "eval" / run_dir(args, arm, seed).name / f"{step:06d}")
        for arm in named for seed in args.seeds for step in steps(arm)
    ]  # fmt: skip
    sweep_all(
        args, [(ckpt, out) for ckpt, out in todo if not swept(out / "results.parquet", ["clean"])], ["clean"]
    )
    for arm, name in named.items():
        rows = []
        for seed in args.seeds:
            log = run_dir(args, arm, seed).resolve().with_suffix(".log")  # a linked run's log is beside it
            for step in steps(arm):
                frame = outcomes(args, arm, seed, step, "clean")
                r = rate(int(frame["success"].sum()), len(frame))
                rows.append(
                    {"minutes": elapsed_minutes(log, step, args.budget[arm][0]), "steps": step,
                     "samples": step * CPU_BATCH_SIZE, "success": r["rate"], "n": r["n"], "ci_low": r["low"],
                     "ci_high": r["high"], "seed": seed}
                )  # fmt: skip
        table = pd.DataFrame(rows)
        path = args.csv.parent / f"{args.task}_{name}.csv"
        table.to_csv(path, index=False, float_format="%.4f")
        plot_success(table, path.with_suffix(".png"), "minutes", CURVE_XLABEL, f"{args.task} {name}")
        print(f"{path}:\n{table.to_string(index=False)}")


def run_all(commands: list[list[str]], jobs: int) -> None:
    """Runs the commands, `jobs` at a time; stops at the first that fails."""
    queue, running = list(commands), []
    while queue or running:
        while queue and len(running) < jobs:
            running.append(subprocess.Popen(queue.pop(0), stdout=subprocess.DEVNULL))
        time.sleep(2)
        for process in [p for p in running if p.poll() is not None]:
            running.remove(process)
            if process.returncode:
                raise SystemExit(f"failed: {shlex.join(process.args)}")


def merge_csv(
    path: Path, rows: list[dict], task: str, names, column: str = "lever", fmt: str = "%.4f", baseline=None
):
    """Writes `rows` to `path` in place of its earlier rows of these names on this task (and against this
    baseline arm, when given: one lever may be paired against two baselines; and under these conditions, when
    the rows have them: a run scored under fewer conditions keeps the others' rows); returns the table."""
    table = pd.DataFrame(rows)
    if path.exists():
        old = pd.read_csv(path)
        replaced = old["task"].eq(task) & old[column].isin(list(names))
        if baseline is not None:
            replaced &= old["baseline_arm"].eq(baseline)
        if "condition" in table and "condition" in old:
            replaced &= old["condition"].fillna("clean").isin(set(table["condition"]))
        table = pd.concat([old[~replaced], table], ignore_index=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    table.to_csv(path, index=False, float_format=fmt)
    return table


def published(args, arm: str) -> bool:
    """Whether the arm's rollouts come from the published tables (--published_baseline) rather than a run."""
    return args.published_baseline and arm == args.baseline


def outcomes(args, arm: str, seed: int, step: int, condition: str) -> pd.DataFrame:
    if published(args, arm):
        path = args.csv.with_name(f"{args.csv.stem}_rollouts.csv")
        table = pd.read_csv(path)
        if "condition" not in table:  # the tables of issue 27 scored clean scenes only
            table = table.assign(condition="clean")
        frame = table[
            table["lever"].eq(arm)
            & table["task"].eq(args.task)
            & table["seed"].eq(seed)
            & table["step"].eq(step)
            & table["condition"].eq(condition)
        ]
        where = f"--published_baseline: {path}"
    else:
        results = args.out / "eval" / run_dir(args, arm, seed).name / f"{step:06d}" / "results.parquet"
        table = read_table(results)
        frame, where = table[table["condition"].eq(condition)], str(results)
    if frame.empty:
        raise SystemExit(
            f"{where} has no rollouts of {arm} on {args.task}, seed {seed}, step {step}, {condition}"
        )
    return frame.sort_values("layout_seed").reset_index(drop=True)


CURVE_XLABEL = "wall-clock minutes of training (one thread, machine shared: see README)"


def plot_success(rows: pd.DataFrame, path: Path, x: str, xlabel: str, title: str, by: str | None = None):
    """Held-out success with its intervals against `x`: one colour per `by` group (a lever) or per seed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = list(rows.groupby(by, sort=False)) if by else [(None, rows)]
    # Levers side by side, spread over 60 % of the gap between checkpoints however many there are.
    gap = (rows[x].max() - rows[x].min()) / max(rows[x].nunique() - 1, 1) * 0.6 / len(groups)
    entries = sum(run["seed"].nunique() for _, run in groups)
    fig, ax = plt.subplots(figsize=(7.5 if by else 6, max(3.5, 0.15 * entries + 0.5)))  # room for the legend
    for i, (name, runs) in enumerate(groups):
        for j, (seed, run) in enumerate(runs.groupby("seed")):
            run = run.sort_values(x)
            ax.errorbar(run[x] + gap * (i - (len(groups) - 1) / 2), run["success"] * 100,
                        yerr=[(run["success"] - run["ci_low"]) * 100, (run["ci_high"] - run["success"]) * 100],
                        color=plt.cm.tab20(i % 20) if by else f"C{j}", marker="os^v"[j % 4], capsize=2,
                        label=f"{name}, seed {seed}" if by else f"seed {seed}")  # fmt: skip
    ax.set(xlabel=xlabel, ylabel="held-out clean success (%)", title=title, ylim=(-5, 105))
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def analyse(args, arms: dict[str, list[str]]) -> None:
    per_checkpoint, pooled, per_rollout, swept_rows = [], {}, [], []
    for arm in arms:
        for condition in args.conditions:
            columns = []
            for seed in args.seeds:
                for step in pooled_steps(args, arm):
                    frame = outcomes(args, arm, seed, step, condition)
                    columns.append(frame[["layout_seed", "success"]].assign(run=seed))
                    if published(args, arm):
                        continue  # its rows are already in the tables
                    swept_rows.append(frame.assign(lever=arm, task=args.task))
                    per_rollout.append(
                        columns[-1].assign(
                            lever=arm, task=args.task, condition=condition, seed=seed, step=step
                        )
                    )
                    r = rate(int(frame["success"].sum()), len(frame))
                    per_checkpoint.append(
                        {"lever": arm, "task": args.task, "condition": condition, "seed": seed, "step": step,
                         "success": r["rate"], "n": r["n"], "ci_low": r["low"], "ci_high": r["high"]}
                    )  # fmt: skip
            pooled[arm, condition] = columns
    rows = []
    for arm in arms:
        if arm == args.baseline:
            continue
        for condition in args.conditions:
            base, treated = pooled[args.baseline, condition], pooled[arm, condition]
            for ours, theirs in zip(base, treated, strict=True):
                if not ours["layout_seed"].equals(theirs["layout_seed"]):
                    raise SystemExit(f"{arm}: the baseline and the lever were evaluated on different layouts")
            a = pd.concat([c["success"] for c in base]).to_numpy()
            b = pd.concat([c["success"] for c in treated]).to_numpy()
            d = paired_difference(a, b)
            # The layout as the pairing unit and the training run as the replicate (issue 57).
            c = clustered_difference(
                *(pd.concat(x).rename(columns={"layout_seed": "layout"}) for x in (base, treated))
            )
            rows.append(
                {"lever": arm, "task": args.task, "condition": condition, "baseline_arm": args.baseline,
                 "seeds": len(args.seeds), "n": d["n"], "baseline": d["rate_a"],
                 "treated": d["rate_b"], "diff": d["diff"], "diff_low": d["low"], "diff_high": d["high"],
                 "p": d["p_value"], "cluster_low": c["low"], "cluster_high": c["high"], "cluster_p": c["p_value"],
                 "seed_effects": " ".join(f"{e:+.4f}" for e in c["seed_effects"]),
                 "flags": shlex.join(arms[arm]), "steps": args.budget[arm][0],
                 "checkpoints": " ".join(map(str, pooled_steps(args, arm)))}
            )  # fmt: skip
    if rows:
        table = merge_csv(args.csv, rows, args.task, [row["lever"] for row in rows], baseline=args.baseline)
        # Holm over the whole table: every comparison ever published in it is one family.
        table.assign(holm_p=holm(table["cluster_p"])).to_csv(args.csv, index=False, float_format="%.4f")
    checkpoints_csv = args.csv.with_name(f"{args.csv.stem}_checkpoints.csv")
    own = [arm for arm in arms if not published(args, arm)]
    mine = merge_csv(checkpoints_csv, per_checkpoint, args.task, own)
    # Every pooled rollout, so a later session can re-pair these arms after outputs/ is gone.
    rollouts = pd.concat(per_rollout, ignore_index=True)[
        ["lever", "task", "condition", "seed", "step", "layout_seed", "success"]
    ]
    merge_csv(
        args.csv.with_name(f"{args.csv.stem}_rollouts.csv"), rollouts.astype({"success": int}).to_dict("records"),
        args.task, own,
    )  # fmt: skip
    # Where each arm fails, per condition: the stage funnel and the competitor's share of the pooled rollouts.
    funnel = cell_metrics(pd.concat(swept_rows, ignore_index=True), by=("lever", "task", "condition"))
    columns = [
        "lever",
        "task",
        "condition",
        "episodes",
        *(f"{m}{s}" for m in METRICS for s in ("", "_k", "_n")),
    ]
    merge_csv(
        args.csv.with_name(f"{args.csv.stem}_funnel.csv"), funnel[columns].to_dict("records"), args.task, own
    )
    clean = mine["condition"].fillna("clean").eq("clean") if "condition" in mine else True
    plot_success(
        mine[mine["task"].eq(args.task) & clean], checkpoints_csv.with_name(f"{args.csv.stem}_{args.task}.png"),
        "step", "training steps", args.task, by="lever",
    )  # fmt: skip
    for (arm, condition), columns in pooled.items():
        r = rate(sum(int(c["success"].sum()) for c in columns), sum(len(c) for c in columns))
        print(
            f"{arm}, {condition}: {r['rate']:.1%} [{r['low']:.1%}, {r['high']:.1%}] of {r['n']} pooled rollouts"
        )
    if rows:
        print(pd.DataFrame(rows).drop(columns=["flags"]).to_string(index=False))
    if args.train_layouts:
        fit_vs_heldout(args, {arm: arms[arm] for arm in own})


def fit_vs_heldout(args, arms: dict[str, list[str]]) -> None:
    """Each run's last checkpoint on the recording's own layouts and on held-out ones, pooled over seeds."""
    rows = []
    for arm in arms:
        for layouts, folder in (("train", "eval_train"), ("heldout", "eval")):
            frames = [
                read_table(
                    args.out
                    / folder
                    / run_dir(args, arm, seed).name
                    / f"{args.budget[arm][0]:06d}"
                    / "results.parquet"
                )
                for seed in args.seeds
            ]
            success = pd.concat(frames)["success"]
            r = rate(int(success.sum()), len(success))
            rows.append(
                {"task": args.task, "variant": args.variant, "config": arm, "step": args.budget[arm][0], "layouts": layouts,
                 "success": r["rate"], "n": r["n"], "ci_low": r["low"], "ci_high": r["high"],
                 "seeds": len(args.seeds)}
            )  # fmt: skip
    merge_csv(args.fit_vs_heldout_csv, rows, args.task, arms, column="config")
    print(pd.DataFrame(rows).to_string(index=False))


def fit_all(args, arms: dict[str, list[str]]) -> None:
    """`condground fit` of every run's last checkpoint on the first demonstrations it trained on and on the
    held-out recording: the teacher-forced error in physical units beside the success it buys."""
    import json

    rows = []
    datasets = {"train": (args.data, args.fit_episodes), "heldout": (args.heldout, "all")}
    for arm in arms:
        for seed in args.seeds:
            for layouts, (root, episodes) in datasets.items():
                out = args.out / "fit" / run_dir(args, arm, seed).name / layouts
                if not (out / "fit.json").exists():
                    subprocess.run(
                        ["condground", "fit", f"--policy.path={checkpoint(run_dir(args, arm, seed), args.budget[arm][0])}",
                         f"--dataset.root={root}", f"--fit.episodes={episodes}", f"--output_dir={out}",
                         "--progress=false"],
                        check=True, stdout=subprocess.DEVNULL,
                    )  # fmt: skip
                for segment, row in json.loads((out / "fit.json").read_text())["segments"].items():
                    rows.append(
                        {"lever": arm, "task": args.task, "seed": seed, "step": args.budget[arm][0], "layouts": layouts,
                         "segment": segment, "frames": row["frames"], "l1": row["l1"], "tcp_cm": row["tcp_cm"],
                         "tcp_cm_p90": row["tcp_cm_p90"], "base_rad": row["joint_rad"][0],
                         "wrist3_rad": row["joint_rad"][5], "gripper": row["gripper"],
                         "head_camera_share_median": row["head_camera_share_median"],
                         "head_camera_share_low": row["head_camera_share_low"], "phase_accuracy": row["phase_accuracy"]}
                    )  # fmt: skip
    mine = merge_csv(args.csv.with_name(f"{args.csv.stem}_fit.csv"), rows, args.task, arms)
    overall = mine[mine["segment"].isin(["all", "grasp"]) & mine["task"].eq(args.task)]
    columns = ["l1", "tcp_cm", "base_rad", "head_camera_share_median", "phase_accuracy"]
    print(overall.groupby(["lever", "layouts", "segment"])[columns].mean().to_string())


def failures_all(args, arms: dict[str, list[str]]) -> None:
    """`condground failures` of every run's last checkpoint on the held-out layouts: each failure's cause."""
    import json

    todo, rows = [], []
    for arm in arms:
        for seed in args.seeds:
            out = args.out / "failures" / run_dir(args, arm, seed).name
            todo.append((arm, seed, out))
    run_all(
        [
            ["condground", "failures", f"--policy.path={checkpoint(run_dir(args, arm, seed), args.budget[arm][0])}",
             f"--env.task={args.task}", f"--env.servo={args.servo}", f"--failures.episodes={args.episodes}",
             f"--failures.seed_offset={args.seed_offset}", f"--output_dir={out}", "--progress=false"]
            for arm, seed, out in todo
            if not (out / "failures.json").exists()
        ],
        args.jobs,
    )  # fmt: skip
    for arm, seed, out in todo:
        result = json.loads((out / "failures.json").read_text())
        offsets, carry = result["first_close_offset_cm"], result["carry"]
        rows.append(
            {"lever": arm, "task": args.task, "seed": seed, "step": args.budget[arm][0], "rollouts": result["rollouts"],
             **result["causes"], "regrasped": result["regrasped"], "stalled": result["stalled"],
             "close_offset_cm_success": offsets["success_median"], "close_offset_cm_failure": offsets["failure_median"],
             "released": carry["released"], "slipped": carry["slipped"], "held_to_end": carry["held_to_end"],
             "release_offset_cm_success": carry["release_offset_cm"]["success_median"],
             "release_offset_cm_failure": carry["release_offset_cm"]["failure_median"]}
        )  # fmt: skip
    merge_csv(args.csv.with_name(f"{args.csv.stem}_failures.csv"), rows, args.task, arms, fmt="%.2f")
    print(pd.DataFrame(rows).to_string(index=False))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--task", required=True)
    parser.add_argument("--data", type=Path, required=True, help="the recording to train on")
    parser.add_argument("--variant", default="standard")
    parser.add_argument("--lever", action="append", default=[], help="NAME=FLAGS (lerobot-train flags)")
    parser.add_argument("--flags", default="", help="flags for every arm, baseline included")
    parser.add_argument(
        "--baseline",
        default="baseline",
        help="the baseline arm's name in run folders and tables (e.g. the "
        "lever an earlier wave adopted, whose runs it reuses)",
    )
    parser.add_argument(
        "--published_baseline",
        action="store_true",
        help="pair against the baseline's rollouts in <csv stem>_rollouts.csv (an earlier session's runs on "
        "the same recording) instead of training and evaluating it again",
    )
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument(
        "--conditions",
        default="clean",
        help="held-out conditions scored and compared (e.g. clean,full_mixed)",
    )
    parser.add_argument("--steps", type=int, default=CPU_STEPS, help="the configuration's budget by default")
    parser.add_argument("--every", type=int, default=2000)
    parser.add_argument("--pool", type=int, default=3, help="last checkpoints of each run pooled")
    parser.add_argument("--episodes", type=int, default=50, help="held-out layouts per checkpoint")
    parser.add_argument("--seed_offset", type=int, default=1_000_000, help="layouts (the sweep's default)")
    parser.add_argument("--servo", default="interpolated")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per training run")
    parser.add_argument("--jobs", type=int, default=2, help="sweeps at once")
    parser.add_argument("--out", type=Path, default=Path("outputs/levers"))
    parser.add_argument("--csv", type=Path, default=Path("docs/learning-curve/v2/levers.csv"))
    parser.add_argument(
        "--train_layouts", type=int, default=0, help="rollouts on the recording's own layouts"
    )
    parser.add_argument(
        "--fit_vs_heldout_csv", type=Path, default=Path("docs/learning-curve/fit_vs_heldout.csv")
    )
    parser.add_argument("--heldout", type=Path, help="a held-out recording of the task (the fit stage)")
    parser.add_argument("--fit_episodes", default="0:20", help="training episodes the fit stage reads")
    parser.add_argument(
        "--stage", choices=("all", "train", "evaluate", "analyse", "fit", "failures", "curve"), default="all"
    )
    parser.add_argument(
        "--curve", action="append", default=[], help="ARM:NAME: the curve stage writes <task>_<NAME>.csv"
    )
    args = parser.parse_args()
    args.seeds = [int(s) for s in args.seeds.split(",")]
    args.conditions = args.conditions.split(",")
    args.flags = shlex.split(args.flags)
    arms = parse_levers(args.lever, args.baseline)
    args.budget = budgets(args, arms)
    runs = {arm: flags for arm, flags in arms.items() if not published(args, arm)}
    if args.stage in ("all", "train"):
        train_all(args, runs)
    if args.stage in ("all", "evaluate"):
        evaluate_all(args, runs)
    if args.stage in ("all", "analyse"):
        analyse(args, arms)
    if args.stage in ("all", "fit") and args.heldout is not None:
        fit_all(args, runs)
    if args.stage in ("all", "failures"):
        failures_all(args, runs)
    if args.stage in ("all", "curve") and args.curve:
        curves(args, runs)


if __name__ == "__main__":
    sys.exit(main())
