"""Config groups every command shares, defined once: a checkpoint reference, an evaluation env, a dataset.

Commands compose them as `--policy.*`, `--env.*`, `--dataset.*` / `--output.*` (LeRobot's flag style).
A command that wants other defaults for a group (diagnose's condition, augment's repo ids) fills them in
its config's `__post_init__`: draccus rebuilds a group from its class defaults as soon as one of the
group's flags is given, so a `default_factory` holding other values would be silently dropped.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import draccus

from lerobot_condground.core.trust import check_dataset_paths

# `condground sweep` draws its held-out layouts from this seed on; recordings start at 0 and stay below it.
HELD_OUT_SEED_OFFSET = 1_000_000
SEED_LIMIT = 2**63  # seeds are stored in int64 columns (results, provenance); numpy refuses negative ones


class ConfigError(draccus.utils.DecodingError):
    """A bad value found by a config's `__post_init__`, for configs the stock scripts parse (`--env.*`,
    `--robot.*`). draccus wraps a ValueError raised there into its generic "Couldn't instantiate class" at
    the end of a long traceback; this one it passes on, and LeRobot's scripts print it as one line,
    `error: <message>`. Not a ValueError for that reason; `condground` reports it like one."""

    def __init__(self, message: str):
        super().__init__((), message)


def usable_cores() -> int:
    """The cores this process may run on: `taskset`, cgroup cpusets and Slurm allocations narrow it below
    `os.cpu_count()`, and sizing workers or threads by the machine's count oversubscribes the allocation."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def check_seed(flag: str, first: int, count: int = 1) -> None:
    """`count` seeds from `first` on must all be valid; one error naming the flag otherwise."""
    if not 0 <= first <= SEED_LIMIT - count:
        raise ValueError(f"{flag}={first} is not allowed; allowed: a seed from 0 to {SEED_LIMIT - count}")


def comma_items(text: str, flag: str, separator: str = ",") -> list[str]:
    """The stripped items of a list flag. An empty item (`a,,b`, a trailing comma) is a typo, not nothing: one
    error naming the flag, before anything runs. Empty text is no items (the caller says what it needs)."""
    text = str(text).strip()
    if not text:
        return []
    items = [t.strip() for t in text.split(separator)]
    if "" in items:
        raise ValueError(
            f"{flag}={text!r} has an empty item; allowed: items separated by single {separator!r}, none empty"
        )
    return items


def check_at_least(group: object, prefix: str, **minimums: float) -> None:
    """Each named field of a config group (flags `--<prefix><name>`) must be at least its minimum; None
    stands for "the default" and passes. NaN fails too."""
    for name, low in minimums.items():
        value = getattr(group, name)
        if value is not None and not value >= low:
            raise ValueError(f"--{prefix}{name}={value} is not allowed; allowed: a number >= {low:g}")


@dataclass
class PolicyRefConfig:
    # A LeRobot checkpoint: a pretrained_model directory or a hub id (offline: from the cache).
    # `expert` is the scripted expert where a command can evaluate it (sweep).
    path: str | None = None
    # Several checkpoints, one per training seed, separated by commas (sweep).
    paths: str | None = None
    # What tables call the policy (default: its type, and the variant for act_modified).
    label: str | None = None
    # cpu, cuda, mps, xpu; default: the best one here (LeRobot's auto_select_torch_device).
    device: str | None = None
    # A checkpoint's processor files may name any Python class, which LeRobot imports and calls; only steps
    # registered by installed code load unless this is true (the hub's convention for running a repo's code).
    trust_remote_code: bool = False

    def checkpoints(self) -> list[str]:
        """Every checkpoint named by --policy.path and --policy.paths, in order."""
        one = [self.path.strip()] if self.path and self.path.strip() else []
        return one + comma_items(self.paths or "", "--policy.paths")

    def single(self) -> str:
        """The one checkpoint of a command that reads one."""
        checkpoints = self.checkpoints()
        if len(checkpoints) != 1:
            raise ValueError(
                f"this command reads one checkpoint; got {len(checkpoints)} ({', '.join(checkpoints) or 'none'}): "
                "give it as --policy.path=DIR_OR_HUB_ID"
            )
        return checkpoints[0]


@dataclass
class EvalEnvConfig:
    task: str = "PickPlaceRandomBin-v0"
    # The scene's condition, for commands that run one (diagnose: the reference of the matched pairs;
    # attention: the scene). Sweeps take theirs from --sweep.conditions, the probe from its role and match.
    condition: str | None = None
    counterbalanced: bool = False
    # Default: each checkpoint's own camera size.
    observation_height: int | None = None
    observation_width: int | None = None
    episode_length: int = 300
    fps: int = 20
    # How joint targets reach the simulated servos: interpolated (as the UR3e) or direct (runs made before).
    servo: str = "interpolated"
    # Camera frames as rendered (none) or through a recorded dataset's video codec (video): see core/codec.py.
    camera_codec: str = "none"
    # Where look-alike competitors come from: eval (the evaluation assets, the protocol's scenes) or
    # augmentation (the copy-paste pool's, as `condground record --env.competitor_pool=augmentation` renders
    # them): scoring a policy trained among those on the same kind of scene tells novel assets from clutter.
    competitor_pool: str = "eval"

    def __post_init__(self):
        from lerobot_condground.core.codec import check_camera_codec

        # Sizes are checked with the checkpoint's when the env is built.
        check_camera_codec(self.camera_codec, "--env.camera_codec")


@dataclass
class DatasetRefConfig:
    # Dataset id; the hub repo id when one is pushed or pulled.
    repo_id: str | None = None
    # Local directory of the dataset (default: $HF_LEROBOT_HOME/<repo_id>).
    root: str | None = None

    def path(self) -> Path:
        """The dataset's root, once its own metadata is known to keep every file inside it."""
        root = Path(self.root) if self.root else self._home_path()
        check_dataset_paths(root)
        return root

    def _home_path(self) -> Path:
        if not self.repo_id:
            raise ValueError("a dataset needs --dataset.repo_id or --dataset.root")
        from huggingface_hub.errors import HFValidationError
        from huggingface_hub.utils import validate_repo_id
        from lerobot.utils.constants import HF_LEROBOT_HOME

        # The id becomes a path under LeRobot's home: '../..' would write anywhere.
        try:
            validate_repo_id(self.repo_id)
        except HFValidationError as err:
            raise ValueError(
                f"repo_id={self.repo_id!r} is not a hub id ({str(err).splitlines()[0]}); allowed: "
                "'name' or 'namespace/name' of letters, digits, '-', '_' and '.' (or give a root)"
            ) from None
        path = HF_LEROBOT_HOME / self.repo_id
        if not path.resolve().is_relative_to(HF_LEROBOT_HOME.resolve()):
            raise ValueError(
                f"repo_id={self.repo_id!r} points outside {HF_LEROBOT_HOME}; give a root instead"
            )
        return path


@dataclass
class DatasetOutputConfig(DatasetRefConfig):
    # Encode camera frames as video (true) or PNG images (false); default: as the command says.
    video: bool | None = None
    push_to_hub: bool = False
    private: bool = False
