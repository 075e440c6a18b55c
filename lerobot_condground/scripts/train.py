"""`condground train`: LeRobot's own training loop with decoded video frames held in memory.

Takes exactly `lerobot-train`'s flags and writes exactly its outputs (it runs LeRobot's `train`), plus one
flag of its own, `--frame_cache_gb` (default 8): the memory decoded frames may take. On this 2-core CPU a
96x128 dataset's frames (100 episodes: about 1.3 GB) then decode once instead of every epoch.
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path

FLAG = "--frame_cache_gb="
DEFAULT_GB = 8.0


def parse(args: list[str]) -> tuple[float, list[str]]:
    sizes = [a.removeprefix(FLAG) for a in args if a.startswith(FLAG)]
    try:
        max_gb = float(sizes[-1]) if sizes else DEFAULT_GB
    except ValueError:
        max_gb = float("nan")
    if not max_gb > 0:
        raise ValueError(f"{FLAG}{sizes[-1]} is not allowed; allowed: a number of GiB > 0")
    # lerobot-train takes a step count below 1 and trains nothing, saving nothing, without a word.
    steps = [a.removeprefix("--steps=") for a in args if a.startswith("--steps=")]
    if steps and not (steps[-1].strip().isdigit() and int(steps[-1]) >= 1):
        raise ValueError(
            f"--steps={steps[-1]} is not allowed; allowed: a whole number of training steps >= 1"
        )
    return max_gb, [a for a in args if not a.startswith(FLAG)]


def main(cfg: tuple[float, list[str]]) -> None:
    from lerobot.scripts import lerobot_train

    from lerobot_condground.datasets.frame_cache import FrameCache

    max_gb, args = cfg
    with FrameCache(max_gb), _metadata_checked():
        sys.argv = ["lerobot-train", *args]
        lerobot_train.main()


@contextlib.contextmanager
def _metadata_checked():
    """The dataset LeRobot opens (by --dataset.root in any spelling, a --config_path, or a hub download into
    $HF_LEROBOT_HOME) keeps every path its metadata templates name inside its root, checked as it is read."""
    from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata

    from lerobot_condground.core.trust import check_dataset_paths

    load = LeRobotDatasetMetadata._load_metadata

    def checked(self, *args, **kwargs):
        load(self, *args, **kwargs)
        check_dataset_paths(Path(self.root))

    LeRobotDatasetMetadata._load_metadata = checked
    try:
        yield
    finally:
        LeRobotDatasetMetadata._load_metadata = load
