"""One checkpoint under both servo modes of the simulation: paired outcomes on the same clean layouts.

    python docs/measurements/servo_check.py --task=PickPlaceFixedBin-v0 \
        --checkpoint=outputs/reproduce/train/PickPlaceFixedBin-v0/augmentation/seed0/checkpoints/009000/pretrained_model \
        --out=outputs/servo --csv=docs/servo/PickPlaceFixedBin-v0_augmentation.csv

`condground sweep` evaluates the checkpoint with `--env.servo=direct` (joint targets set at once, as every
run before the setting) and `--env.servo=interpolated` (the default: the UR3e's servo stream) on the same
layouts; a rerun reuses finished sweeps. Prints and writes, per outcome, both rates with 95 % Wilson
intervals and interpolated − direct (Newcombe interval, exact McNemar p), and how often the cube ended off
the table (below it, or more than 1 m from the arm's base).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
from clean_sweep import clean_sweep

from lerobot_condground.evaluation.statistics import paired_difference, rate

MODES = ("direct", "interpolated")


def sweep(args, servo: str) -> pd.DataFrame:
    flags = [f"--env.servo={servo}", f"--eval.seeds={args.seeds}", f"--eval.n_episodes={args.episodes}"]
    return clean_sweep(args.checkpoint, args.task, args.out / servo, *flags, f"--workers={args.workers}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--task", required=True)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--episodes", type=int, default=50, help="rollouts per evaluation seed")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--csv", type=Path)
    args = parser.parse_args()

    direct, interpolated = (sweep(args, servo) for servo in MODES)
    if direct.layout_seed.tolist() != interpolated.layout_seed.tolist():
        raise ValueError(f"the sweeps in {args.out} ran other layouts; remove them or choose another --out")
    frames = {"direct": direct, "interpolated": interpolated}
    for frame in frames.values():
        frame["off_table"] = (frame.target_z < -0.05) | (np.hypot(frame.target_x, frame.target_y) > 1)
    rows = []
    for outcome in ("success", "pick", "lift", "off_table"):
        diff = paired_difference(direct[outcome].to_numpy(bool), interpolated[outcome].to_numpy(bool))
        row = {"outcome": outcome, "n": diff["n"]}
        for servo, frame in frames.items():
            r = rate(int(frame[outcome].sum()), len(frame))
            row |= {servo: r["rate"], f"{servo}_low": r["low"], f"{servo}_high": r["high"]}
        rows.append(row | {"diff": diff["diff"], "diff_low": diff["low"], "diff_high": diff["high"],
                           "mcnemar_p": diff["p_value"]})  # fmt: skip
    table = pd.DataFrame(rows)
    print(table.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    if args.csv:
        args.csv.parent.mkdir(parents=True, exist_ok=True)
        table.to_csv(args.csv, index=False, float_format="%.4f")


if __name__ == "__main__":
    main()
