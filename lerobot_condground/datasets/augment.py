"""`condground augment`: an augmented copy of a LeRobotDataset, for policies that train on it as is.

Every frame of the source goes through the copy-paste step's `augment` (the same code the
`act_modified` preprocessor runs during training), and is written under a new repo id with the same
features, fps, robot type and, unless told otherwise, the same video setting. Pasted pixels are
labeled `SYNTHETIC_DISTRACTOR` in `observation.segmentation`. Camera frames are decoded from the
source and, with video, encoded again: pixels outside the pastes match the source up to that codec.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from lerobot_condground.core.configs import DatasetOutputConfig, DatasetRefConfig
from lerobot_condground.core.files import partial_beside
from lerobot_condground.core.labels import OBS_SEGMENTATION, SYNTHETIC_DISTRACTOR, decode_labels, encode_png
from lerobot_condground.core.provenance import AUGMENT_FILE, RECORD_FILE
from lerobot_condground.core.scheduling import kept_priority
from lerobot_condground.processors.copy_paste import CopyPasteDistractorStep, CopyPasteParams


@dataclass
class AugmentConfig:
    # Default repo ids: local/condground_pickplace (what `condground record` writes by default) and
    # local/condground_pickplace_augmented.
    dataset: DatasetRefConfig = field(default_factory=DatasetRefConfig)
    # Must not exist yet. video: default as in the source.
    output: DatasetOutputConfig = field(default_factory=DatasetOutputConfig)
    copy_paste: CopyPasteParams = field(default_factory=CopyPasteParams)
    # Frames augmented together (one batch of the step).
    batch_size: int = 16
    progress: bool = True

    def __post_init__(self):
        # This command's defaults for the shared groups (see core/configs.py on why not a default_factory).
        self.dataset.repo_id = self.dataset.repo_id or "local/condground_pickplace"
        self.output.repo_id = self.output.repo_id or "local/condground_pickplace_augmented"
        if self.copy_paste.warmup_steps:
            raise ValueError(
                f"--copy_paste.warmup_steps={self.copy_paste.warmup_steps} ramps pastes in over training batches, "
                "and an offline augmentation has none; allowed: 0"
            )


def _open_source(cfg: AugmentConfig):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = cfg.dataset.path()
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(
            f"--dataset.root={root} holds no LeRobotDataset (no meta/info.json); allowed: the root of a local "
            f"dataset, e.g. one written by `condground record`"
        )
    dataset = LeRobotDataset(cfg.dataset.repo_id, root=root)
    features = dataset.meta.features
    camera = cfg.copy_paste.camera_key
    if camera not in dataset.meta.camera_keys:
        raise ValueError(
            f"--copy_paste.camera_key={camera!r} is not a camera of {root}; allowed: "
            f"{', '.join(dataset.meta.camera_keys) or '(the dataset has no camera)'}"
        )
    if OBS_SEGMENTATION not in features:
        raise ValueError(
            f"{root} has no {OBS_SEGMENTATION!r} feature, which the augmentation needs to spare the "
            f"targets and label the pastes; allowed: a dataset recorded with segmentation "
            f"(`condground record`, or labels from SAM 2)"
        )
    return dataset, root


def _output_features(source, video: bool) -> dict:
    from lerobot.utils.constants import DEFAULT_FEATURES

    out = {}
    for key, ft in source.meta.features.items():
        if key in DEFAULT_FEATURES:
            continue
        dtype = ("video" if video else "image") if key in source.meta.camera_keys else ft["dtype"]
        out[key] = {"dtype": dtype, "shape": tuple(ft["shape"]), "names": ft.get("names")}
    return out


def _frame(item: dict, features: dict, cameras: list[str]) -> dict:
    """A dataset item (as LeRobotDataset returns it) back into `add_frame`'s form."""
    frame = {"task": item["task"]}
    for key, ft in features.items():
        value = item[key]
        if key in cameras:
            frame[key] = (value.permute(1, 2, 0) * 255).round().clamp(0, 255).to(torch.uint8).numpy()
        elif ft["dtype"] == "string":
            frame[key] = value
        else:
            frame[key] = np.asarray(value).reshape(ft["shape"]).astype(ft["dtype"])
    return frame


def augment_dataset(cfg: AugmentConfig) -> dict:
    """Writes the augmented copy; returns counts for the summary."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from tqdm import tqdm

    if cfg.batch_size < 1:  # checked here, not in __post_init__, where draccus would bury the message
        raise ValueError(f"--batch_size={cfg.batch_size} is not allowed; allowed: an integer >= 1")
    step = CopyPasteDistractorStep(segmentation_key=OBS_SEGMENTATION, **asdict(cfg.copy_paste))
    out_root = cfg.output.path()
    if out_root.exists():
        raise FileExistsError(
            f"--output.root={out_root} already exists; allowed: a path that does not exist yet "
            f"(the augmented copy is always written fresh)"
        )
    source, src_root = _open_source(cfg)
    if out_root.resolve() == src_root.resolve():
        raise ValueError(f"--output.root={out_root} is the source dataset; allowed: another path")
    video = bool(source.meta.video_keys) if cfg.output.video is None else cfg.output.video
    features = _output_features(source, video)
    cameras = list(source.meta.camera_keys)
    camera = cfg.copy_paste.camera_key
    partial = partial_beside(out_root)
    target = LeRobotDataset.create(
        cfg.output.repo_id,
        fps=source.meta.fps,
        features=features,
        root=partial,
        robot_type=source.meta.robot_type,
        use_videos=video,
        streaming_encoding=False,
    )
    frames = pasted_frames = pasted_pixels = 0
    episodes = source.meta.episodes
    bar = tqdm(
        total=source.meta.total_frames,
        desc=f"augment {cfg.dataset.repo_id}",
        unit="frame",
        disable=not cfg.progress,
    )
    finished = False
    try:
        for ep in range(source.meta.total_episodes):
            start, stop = int(episodes[ep]["dataset_from_index"]), int(episodes[ep]["dataset_to_index"])
            for first in range(start, stop, cfg.batch_size):
                items = [source[i] for i in range(first, min(first + cfg.batch_size, stop))]
                images = torch.stack([item[camera] for item in items])
                seg = torch.stack([decode_labels(item)[OBS_SEGMENTATION] for item in items])
                images, seg = step.augment(images, seg)
                synthetic = (seg == SYNTHETIC_DISTRACTOR).flatten(1).sum(1)
                pasted_frames += int((synthetic > 0).sum())
                pasted_pixels += int(synthetic.sum())
                for item, image, labels in zip(items, images, seg):
                    labels = encode_png(labels.numpy())
                    target.add_frame(
                        _frame({**item, camera: image, OBS_SEGMENTATION: labels}, features, cameras)
                    )
                frames += len(items)
                bar.update(len(items))
            with kept_priority():  # the encoder would leave this thread at real-time priority
                target.save_episode()
        finished = True
    finally:
        bar.close()
        with kept_priority():
            target.finalize()
        if not finished:
            shutil.rmtree(partial, ignore_errors=True)
    if (src_root / RECORD_FILE).is_file():
        shutil.copyfile(src_root / RECORD_FILE, partial / RECORD_FILE)
    (partial / AUGMENT_FILE).write_text(
        json.dumps(
            {
                "source": {"repo_id": cfg.dataset.repo_id, "root": str(src_root)},
                "copy_paste": step.get_config(),
            },
            indent=1,
        )
    )
    partial.rename(out_root)
    if cfg.output.push_to_hub:
        LeRobotDataset(cfg.output.repo_id, root=out_root).push_to_hub(private=cfg.output.private)
    return {
        "episodes": source.meta.total_episodes,
        "frames": frames,
        "pasted_frames": pasted_frames,
        "pasted_pixels": pasted_pixels,
        "root": str(out_root),
        "repo_id": cfg.output.repo_id,
    }


def format_summary(result: dict) -> str:
    share = result["pasted_frames"] / max(result["frames"], 1)
    per_frame = result["pasted_pixels"] / max(result["pasted_frames"], 1)
    return (
        f"augmented {result['episodes']} episodes, {result['frames']} frames -> {result['repo_id']} at "
        f"{result['root']}\nframes with pastes: {result['pasted_frames']} ({share:.0%}), "
        f"{per_frame:.0f} synthetic-distractor pixels per such frame"
    )
