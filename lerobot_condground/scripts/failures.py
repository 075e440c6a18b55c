"""`condground failures`: each failed rollout of a checkpoint classified by cause, with its grasp offsets."""

from lerobot_condground.diagnosis.failures import FailuresConfig as Config, run_failures


def main(cfg: Config) -> None:
    run_failures(cfg)
