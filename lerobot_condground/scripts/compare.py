"""`condground compare`: one training recipe against another (trained side by side, N seeds, late checkpoints
pooled on the same held-out layouts), with the layout-clustered, run-aware interval.

condground compare --env.task=T --dataset.root=DATA --baseline.name=standard \\
    --treated.name=augmentation --treated.flags='--policy.variant=augmentation' --train.seeds=0,1 \\
    --eval.conditions=clean,full_mixed --output_dir=outputs/compare [--table=docs/.../levers.csv]
"""

from lerobot_condground.experiments.compare import CompareConfig as Config, run


def main(cfg: Config) -> None:
    summary = run(cfg)
    if summary is not None:
        print(summary.drop(columns=["flags"]).to_string(index=False))
