"""The lever commands of docs/learning-curve/ (issue 27's flags), as calls of `condground compare`: one
comparison of the baseline against each --lever, in order, into the same --csv table and --out folder.

    python docs/learning-curve/levers.py --task=PickPlaceFixedBin-v0 --data=outputs/levers/data/PickPlaceFixedBin-v0_dart06_200 \\
        --baseline=actsize_6k --lever='augmentation=--policy.variant=augmentation' --seeds=0,1 --steps=6000 \\
        --every=1000 --conditions=clean,full_mixed --out=outputs/levers28 --csv=docs/learning-curve/v3/levers.csv

prints and runs

    condground compare --env.task=... --dataset.root=... --baseline.name=actsize_6k --treated.name=augmentation
        --treated.flags=--policy.variant=augmentation --train.seeds=0,1 ... --table=docs/learning-curve/v3/levers.csv

Run folders and tables are the ones the example wrote before it became a caller, so a published run resumes
and a published table is updated in place. With --published_baseline the baseline's pooled rollouts come
from `<csv stem>_rollouts.csv`. The stages `curve`, `fit` (--heldout) and --train_layouts of the published
v2 tables are at commit 61ae7c7 of this file; `condground compare --help` lists what a comparison takes.
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys

from lerobot_condground.core.provenance import console_script
from lerobot_condground.core.training import CPU_STEPS


def commands(args) -> list[list[str]]:
    out = []
    for spec in args.lever:
        name, sep, flags = spec.partition("=")
        if not sep:
            raise SystemExit(f"--lever={spec!r}: expected NAME=FLAGS")
        baseline = (
            [f"--baseline.rollouts={args.csv.removesuffix('.csv')}_rollouts.csv"]
            if args.published_baseline
            else []
        )
        out.append([
            console_script("condground"), "compare", f"--env.task={args.task}", f"--env.servo={args.servo}",
            f"--dataset.root={args.data}", f"--baseline.name={args.baseline}", *baseline,
            f"--treated.name={name}", f"--treated.flags={flags}", f"--train.seeds={args.seeds}",
            f"--train.steps={args.steps}", f"--train.save_freq={args.every}", f"--train.variant={args.variant}",
            f"--train.flags={args.flags}", f"--train.threads={args.threads}", f"--eval.conditions={args.conditions}",
            f"--eval.episodes={args.episodes}", f"--eval.seed_offset={args.seed_offset}", f"--eval.pool={args.pool}",
            f"--eval.jobs={args.jobs}", f"--output_dir={args.out}", f"--table={args.csv}", f"--stage={args.stage}",
            f"--failures={str(args.stage == 'all').lower()}",
            f"--allow_differences={str(args.allow_differences).lower()}", "--progress=false",
        ])  # fmt: skip
    return out


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--task", required=True)
    parser.add_argument("--data", required=True, help="the recording to train on")
    parser.add_argument("--variant", default="standard")
    parser.add_argument("--lever", action="append", required=True, help="NAME=FLAGS (lerobot-train flags)")
    parser.add_argument("--flags", default="", help="flags for every arm, baseline included")
    parser.add_argument("--baseline", default="baseline")
    parser.add_argument("--published_baseline", action="store_true")
    parser.add_argument("--allow_differences", action="store_true", help="a lever that is a budget or data")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--conditions", default="clean")
    parser.add_argument("--steps", type=int, default=CPU_STEPS)
    parser.add_argument("--every", type=int, default=2000)
    parser.add_argument("--pool", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed_offset", type=int, default=1_000_000)
    parser.add_argument("--servo", default="interpolated")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", default="outputs/levers")
    parser.add_argument("--csv", default="docs/learning-curve/v2/levers.csv")
    parser.add_argument("--stage", choices=("all", "train", "evaluate", "analyse", "failures"), default="all")
    for command in commands(parser.parse_args()):
        print(shlex.join(command), flush=True)
        if subprocess.run(command).returncode:
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
