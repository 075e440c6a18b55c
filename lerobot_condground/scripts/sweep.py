"""`condground sweep`: checkpoints × conditions × evaluation seeds × rollouts -> results.parquet."""

from lerobot_condground.evaluation.sweep import SweepConfig as Config, run_sweep


def main(cfg: Config) -> None:
    run_sweep(cfg)
