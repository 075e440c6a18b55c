"""`condground reproduce`: the paper's whole experiment at a chosen scale, resumable at every stage.

condground reproduce --preset=cpu|paper --output_dir=DIR [--dry_run=true] [--train.steps=N ...]
"""

import sys

from lerobot_condground.experiments.plan import ReproduceConfig as Config
from lerobot_condground.experiments.reproduce import StageFailedError, run


def main(cfg: Config) -> None:
    try:
        run(cfg)
    except StageFailedError as err:
        print(f"condground reproduce: {err}", file=sys.stderr)
        sys.exit(1)
