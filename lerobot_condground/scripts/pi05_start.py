"""`condground pi05-start`: a starting checkpoint for fine-tuning `pi05_grounded` with the stock `lerobot-train`.

    condground pi05-start --policy.path=lerobot/pi05_base --dataset.repo_id=USER/routing \\
        --output_dir=outputs/pi05_start [--policy.variant=cue] [--policy.tokenizer_name=DIR] [--policy.<field>=...]
    lerobot-train --policy.path=outputs/pi05_start --dataset.repo_id=USER/routing ...

`--policy.*` flags other than `path` set fields of `pi05_grounded` (variant, tokenizer, grounding weights,
layers, heads, dtype, gradient checkpointing, ...) on top of the source checkpoint's configuration.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import draccus

PATH_FLAG = "--policy.path="


@dataclass
class DatasetRef:
    repo_id: str = ""
    root: Path | None = None


@dataclass
class PolicySource:
    # The source: a pi05 checkpoint, a hub id (lerobot/pi05_base) or a local directory. Every other
    # --policy.<field>=value sets that field of pi05_grounded (variant, tokenizer_name, grounding_layers, ...).
    path: str = ""


@dataclass
class Config:
    output_dir: Path = Path("outputs/pi05_start")
    dataset: DatasetRef = field(default_factory=DatasetRef)
    policy: PolicySource = field(default_factory=PolicySource)
    # Filled by `parse`: the `--policy.*` overrides, set on pi05_grounded's configuration.
    policy_overrides: list[str] = field(default_factory=list)

    @property
    def source(self) -> str:
        return self.policy.path


def parse(args: list[str]) -> Config:
    sources = [a.removeprefix(PATH_FLAG) for a in args if a.startswith(PATH_FLAG)]
    overrides = [
        "--" + a.removeprefix("--policy.")
        for a in args
        if a.startswith("--policy.") and a not in (f"{PATH_FLAG}{s}" for s in sources)
    ]
    # The overrides are pi05_grounded's fields, which draccus would refuse as fields of PolicySource.
    cfg = draccus.parse(
        Config,
        args=[a for a in args if not a.startswith("--policy.")],
        prog="condground pi05-start",
    )
    if not sources or not sources[-1]:
        raise ValueError(
            "--policy.path is required: a pi05 checkpoint, hub id (lerobot/pi05_base) or local directory"
        )
    if not cfg.dataset.repo_id:
        raise ValueError(
            "--dataset.repo_id is required: the LeRobotDataset to fine-tune on (its features and statistics)"
        )
    cfg.policy.path, cfg.policy_overrides = sources[-1], overrides
    return cfg


def main(cfg: Config) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    from lerobot_condground.core.trust import check_dataset_paths
    from lerobot_condground.policies.pi05_grounded.starting import write_starting_checkpoint

    if cfg.dataset.root:
        check_dataset_paths(Path(cfg.dataset.root))
    meta = LeRobotDatasetMetadata(cfg.dataset.repo_id, root=cfg.dataset.root)
    config = write_starting_checkpoint(cfg.source, cfg.policy_overrides, meta, cfg.output_dir)
    root = f" --dataset.root={cfg.dataset.root}" if cfg.dataset.root else ""
    print(
        f"Wrote {cfg.output_dir}: pi05_grounded (variant {config.variant}, cameras {', '.join(config.image_features)}, "
        f"tokenizer {config.tokenizer_name}) starting from {cfg.source}.\n"
        f"Fine-tune with:\n  lerobot-train --policy.path={cfg.output_dir} --dataset.repo_id={cfg.dataset.repo_id}{root} "
        "--output_dir=outputs/train/pi05_grounded --policy.repo_id=USER/pi05_grounded"
    )
