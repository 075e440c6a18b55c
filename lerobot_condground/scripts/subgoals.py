"""`condground subgoals`: InstrumentRouting-v0 per subgoal under the VLA study's conditions (simulation, or the
UR3e scored by an operator) -> results.parquet and a subgoal x condition table."""

from lerobot.cameras.opencv import (
    OpenCVCameraConfig,  # noqa: F401  (--robot.cameras types, as lerobot-record)
)

from lerobot_condground.evaluation.subgoals import SubgoalsConfig as Config, run_subgoals


def main(cfg: Config) -> None:
    run_subgoals(cfg)
