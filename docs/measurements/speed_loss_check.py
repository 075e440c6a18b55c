"""Whether a speed option changes what a run learns: the training loss of its first steps beside the current path.

    python docs/measurements/speed_loss_check.py --data=outputs/levers/data/PickPlaceFixedBin-v0_dart06_200 \
        --out=outputs/speed_check --csv=docs/measurements/speed_loss_500.csv

Trains `standard` at the CPU configuration (`core.training`) for `--steps` steps (the cosine's linear warm-up
is the same for any budget up to its 500 warm-up steps), one run at a time on one torch thread: the current
path at two seeds (the seeds' spread is the noise a changed path is read against), then each option at the
first seed. Writes the logged L1 loss (the mean over each `--log_freq` steps) per run and step, and prints per
run its mean over the last half and its largest gap to the first seed's curve beside the two seeds' gap.
A finished run's log is reused.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
from pathlib import Path

import pandas as pd

from lerobot_condground.core.provenance import console_script
from lerobot_condground.core.training import CPU_BATCH_SIZE, policy_flags

RUNS = {
    "fp32": [],
    "channels_last": ["--policy.channels_last=true"],
    "bf16_channels_last": ["--policy.channels_last=true", "--policy.use_amp=true"],
}
LOSS = re.compile(r"step:(\S+) .*? loss:(\S+) .*?updt_s:(\S+)")


def run(args, name: str, seed: int) -> Path:
    out = args.out / f"{name}_s{seed}"
    log = out.with_suffix(".log")
    if log.exists() and (out / "checkpoints" / "last").exists():
        return log
    command = [
        console_script("condground"), "train", "--policy.type=act_modified", "--policy.variant=standard",
        "--policy.device=cpu", "--policy.push_to_hub=false", *policy_flags(), *RUNS[name],
        f"--batch_size={CPU_BATCH_SIZE}", f"--dataset.repo_id=local/{args.task}", f"--dataset.root={args.data}",
        f"--steps={args.steps}", f"--save_freq={args.steps}", f"--log_freq={args.log_freq}", "--num_workers=0",
        "--wandb.enable=false", f"--seed={seed}", f"--output_dir={out}",
    ]  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    with open(log, "w") as f:
        subprocess.run(command, stdout=f, stderr=subprocess.STDOUT, env=env, check=True)
    return log


def steps_of(text: str) -> int:
    return int(float(text[:-1]) * 1000) if text.endswith("K") else int(text)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--task", default="PickPlaceFixedBin-v0")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--csv", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--log_freq", type=int, default=25)
    parser.add_argument("--seeds", default="0,1")
    args = parser.parse_args()
    first, *others = [int(s) for s in args.seeds.split(",")]
    rows = []
    for name, seed in [
        ("fp32", first),
        *(("fp32", s) for s in others),
        *((n, first) for n in RUNS if n != "fp32"),
    ]:
        for match in LOSS.finditer(run(args, name, seed).read_text()):
            step, loss, update_s = match.groups()
            rows.append(
                {
                    "run": name,
                    "seed": seed,
                    "step": steps_of(step),
                    "loss": float(loss),
                    "update_s": float(update_s),
                }
            )
    table = pd.DataFrame(rows)
    table.to_csv(args.csv, index=False, float_format="%.5f")
    curves = table.pivot_table(index="step", columns=["run", "seed"], values="loss")
    reference = curves[("fp32", first)]
    late = curves.index > args.steps / 2
    for (name, seed), curve in curves.items():
        gap = (curve - reference).abs()
        print(
            f"{name} seed {seed}: loss over the last half {curve[late].mean():.4f}, largest gap to fp32 seed {first} "
            f"{gap.max():.4f} (last half {gap[late].max():.4f}), update {table[(table.run == name) & (table.seed == seed)].update_s.median():.3f} s"
        )


if __name__ == "__main__":
    main()
