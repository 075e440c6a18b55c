"""`condground reproduce`: the paper's whole experiment at a chosen scale, resumable at every stage.

condground reproduce --preset=cpu|paper --output_dir=DIR [--dry_run=true] [--train.steps=N ...]
"""

from lerobot_condground.experiments.plan import ReproduceConfig as Config
from lerobot_condground.experiments.reproduce import run


def main(cfg: Config) -> None:
    run(cfg)
