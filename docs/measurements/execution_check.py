"""Same weights, other ways of executing ACT's action chunk: paired clean success on the same layouts.

    python docs/measurements/execution_check.py --checkpoint=.../checkpoints/0009000/pretrained_model \
        --task=PickPlaceFixedBin-v0 --out=outputs/execution --csv=docs/learning-curve/execution.csv \
        --baseline=outputs/learning-curve/eval/PickPlaceFixedBin-v0_standard/0009000

Each variant is a copy of the checkpoint whose config.json executes the chunk differently (ACT's
`n_action_steps`, or temporal ensembling with `temporal_ensemble_coeff` and one step); `condground sweep`
evaluates it on the clean layouts the unmodified checkpoint was evaluated on (`--baseline`: that sweep's
output directory, made with the same --episodes; without it, the unmodified checkpoint is swept too).
Prints and writes, per variant, success with its 95 % Wilson interval and the paired difference to the
checkpoint as trained (Newcombe interval, exact McNemar p).
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import pandas as pd
from clean_sweep import clean_sweep

from lerobot_condground.evaluation.statistics import cell_metrics, paired_difference

# name -> config changes; ACT requires n_action_steps == 1 with temporal ensembling.
VARIANTS = {
    "temporal_ensembling": {"temporal_ensemble_coeff": 0.01, "n_action_steps": 1},
    "n_action_steps_5": {"temporal_ensemble_coeff": None, "n_action_steps": 5},
    "n_action_steps_20": {"temporal_ensemble_coeff": None, "n_action_steps": 20},
}


def variant_checkpoint(source: Path, out: Path, changes: dict) -> Path:
    target = out / "pretrained_model"
    if not target.exists():
        shutil.copytree(source, target)
        config = json.loads((target / "config.json").read_text())
        config.update(changes)
        (target / "config.json").write_text(json.dumps(config, indent=2))
    return target


def sweep(checkpoint: Path, task: str, episodes: int, out: Path) -> pd.DataFrame:
    return clean_sweep(checkpoint, task, out, "--eval.seeds=1", f"--eval.n_episodes={episodes}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--task", required=True)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--baseline", type=Path, help="sweep output of the unmodified checkpoint")
    parser.add_argument("--csv", type=Path)
    args = parser.parse_args()

    base = sweep(args.checkpoint, args.task, args.episodes, args.baseline or args.out / "as_trained")
    trained = json.loads((args.checkpoint / "config.json").read_text())
    rows = []
    for name, changes in {"as_trained": {}, **VARIANTS}.items():
        if changes:
            ckpt = variant_checkpoint(args.checkpoint, args.out / name, changes)
            frame = sweep(ckpt, args.task, args.episodes, args.out / "eval" / name)
        else:
            frame = base
        if frame.layout_seed.tolist() != base.layout_seed.tolist():
            raise ValueError(
                f"{name} was evaluated on other layouts than --baseline; use the same --episodes"
            )
        metrics = cell_metrics(frame).iloc[0]
        diff = paired_difference(frame.success.to_numpy(bool), base.success.to_numpy(bool))
        settings = {**trained, **changes}
        rows.append(
            {
                "execution": name,
                "n_action_steps": settings["n_action_steps"],
                "temporal_ensemble_coeff": settings["temporal_ensemble_coeff"],
                "success": metrics["success"],
                "n": int(metrics["success_n"]),
                "ci_low": metrics["success_low"],
                "ci_high": metrics["success_high"],
                "p_pick": metrics["p_pick"],
                # paired_difference(a, b) is b - a: this variant minus the checkpoint as trained.
                "diff": 0.0 - diff["diff"],
                "diff_low": -diff["high"],
                "diff_high": -diff["low"],
                "mcnemar_p": diff["p_value"],
            }
        )
    table = pd.DataFrame(rows)
    print(table.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    if args.csv:
        args.csv.parent.mkdir(parents=True, exist_ok=True)
        table.to_csv(args.csv, index=False, float_format="%.4f")


if __name__ == "__main__":
    main()
