"""`condground view`: one episode in rerun, with the labels this project adds.

`lerobot-dataset-viz` shows a LeRobotDataset's cameras, state and action; it cannot show what makes our
datasets ours. This logs, on the `frame_index` timeline:
every camera as an image with its segmentation over it (a `SegmentationImage` under an annotation context
that names and colours the labels), the phase as a scalar, the prompt crops as images, state and action
per joint, laid out by a default blueprint. From the outputs of `condground attention`: its overlay video,
the supervised head's attention map, the expert's stage, the predicted phase and the attention mass on
each entity. Writes `--output=FILE.rrd`, or spawns a viewer when no output is given.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lerobot_condground.core.configs import DatasetRefConfig
from lerobot_condground.core.labels import (
    OBS_PHASE,
    OBS_SEGMENTATION,
    OBS_SEGMENTATION_WRIST,
    PNG_LABEL_KEYS,
    SYNTHETIC_DISTRACTOR,
    TARGET_OBJECT,
    TARGET_RECEPTACLE,
    decode_png,
)

# Label ids of a segmentation map (core/labels.py) and the colours the viewer gives them.
LABELS = [
    (0, "background and robot", (0, 0, 0, 0)),  # transparent: the camera shows through
    (TARGET_OBJECT, "target object", (230, 57, 70)),
    (TARGET_RECEPTACLE, "target receptacle", (29, 120, 230)),
    *[
        (3 + i, f"competitor {i + 1}", color)
        for i, color in enumerate(
            [(255, 183, 3), (142, 202, 230), (131, 56, 236), (251, 133, 0), (33, 158, 188)]
        )
    ],  # fmt: skip
    (SYNTHETIC_DISTRACTOR, "pasted distractor", (255, 0, 255)),
]


# Each segmentation is logged under its camera, so the camera's view overlays it.
SEGMENTATION_CAMERA = {OBS_SEGMENTATION: "top", OBS_SEGMENTATION_WRIST: "wrist"}


@dataclass
class ViewConfig:
    dataset: DatasetRefConfig = field(default_factory=DatasetRefConfig)
    episode: int = 0
    # Output directory of `condground attention` (instead of a dataset).
    attention_dir: str | None = None
    # A .rrd file to write; without it a rerun viewer is spawned.
    output: str | None = None
    progress: bool = True


# The first bytes of every .rrd file rerun writes.
RRD_MAGIC = b"RRF2"


def _start(name: str, output: str | None, blueprint=None):
    import rerun as rr

    rr.init(name, spawn=False)
    if output is None:
        rr.spawn(default_blueprint=blueprint)
    else:
        Path(output).parent.mkdir(parents=True, exist_ok=True)
        rr.save(output, default_blueprint=blueprint)
    return rr


def _dataset_blueprint(cameras: list[str], prompts: list[str], phase: bool):
    """Cameras with their segmentation overlaid and the prompt crops on the left; state, action and phase
    as one plot each on the right."""
    import rerun.blueprint as rrb

    images = [rrb.Spatial2DView(origin=f"cameras/{c}", name=c) for c in cameras]
    crops = [rrb.Spatial2DView(origin=f"prompts/{p}", name=f"prompt: {p}") for p in prompts]
    plots = [
        rrb.TimeSeriesView(origin=o, name=o)
        for o in ("state", "action", *(["labels/phase"] if phase else []))
    ]
    left = (
        rrb.Vertical(rrb.Horizontal(*images), rrb.Horizontal(*crops), row_shares=[3, 1])
        if crops
        else rrb.Horizontal(*images)
    )
    return rrb.Blueprint(
        rrb.Horizontal(left, rrb.Vertical(*plots), column_shares=[3, 2]), collapse_panels=True
    )


def _rgb(frame) -> np.ndarray:
    """A LeRobot camera frame (C, H, W) float in [0, 1] as (H, W, 3) uint8."""
    array = frame.numpy() if hasattr(frame, "numpy") else np.asarray(frame)
    return (np.clip(array.transpose(1, 2, 0), 0, 1) * 255).round().astype(np.uint8)


def _scalars(rr, path: str, values, names: list[str] | None) -> None:
    values = np.atleast_1d(np.asarray(values, dtype=np.float64))
    if names and len(names) == len(values):
        for name, value in zip(names, values, strict=True):
            rr.log(f"{path}/{name}", rr.Scalars([value]))
    else:
        rr.log(path, rr.Scalars(values))


def view_dataset(cfg: ViewConfig) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata

    root = cfg.dataset.path()
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(f"--dataset.root={root} holds no LeRobotDataset (no meta/info.json)")
    repo_id = cfg.dataset.repo_id or f"local/{root.name}"
    meta = LeRobotDatasetMetadata(repo_id, root=root)
    if not 0 <= cfg.episode < meta.total_episodes:
        raise ValueError(
            f"--episode={cfg.episode} is not allowed; allowed: 0 to {meta.total_episodes - 1} "
            f"({meta.total_episodes} episodes in {root})"
        )
    labels = [key for key in (*PNG_LABEL_KEYS, OBS_PHASE) if key in meta.features]
    if not labels:
        raise ValueError(
            f"{root} has no label features ({', '.join((*PNG_LABEL_KEYS, OBS_PHASE))}): it was recorded "
            "with --dataset.labels=false or by another tool; `lerobot-dataset-viz` shows its cameras, state "
            "and action"
        )
    dataset = LeRobotDataset(repo_id, root=root, episodes=[cfg.episode])
    cameras = [key.removeprefix("observation.images.") for key in meta.camera_keys]
    prompts = [
        key.removeprefix("observation.prompt.") for key in labels if key.startswith("observation.prompt.")
    ]
    blueprint = _dataset_blueprint(cameras, prompts, OBS_PHASE in labels)
    rr = _start(f"{repo_id}/episode_{cfg.episode}", cfg.output, blueprint)
    rr.log("cameras", rr.AnnotationContext(LABELS), static=True)
    names = {key: (meta.features[key].get("names") or None) for key in ("observation.state", "action")}
    for i in tqdm(range(len(dataset)), desc=f"episode {cfg.episode}", unit="frame", disable=not cfg.progress):
        item = dataset[i]
        rr.set_time("frame_index", sequence=int(item["frame_index"]))
        rr.set_time("timestamp", duration=float(item["timestamp"]))
        for key in meta.camera_keys:
            rr.log(f"cameras/{key.removeprefix('observation.images.')}", rr.Image(_rgb(item[key])))
        for key in labels:
            value = item[key]
            if key == OBS_PHASE:
                rr.log("labels/phase", rr.Scalars([float(np.asarray(value).reshape(-1)[0])]))
                continue
            image = decode_png(value if isinstance(value, str) else value[0])
            if image.ndim == 2:  # a label map
                rr.log(
                    f"cameras/{SEGMENTATION_CAMERA[key]}/segmentation",
                    rr.SegmentationImage(image, opacity=0.6),
                )
            else:  # a prompt crop
                rr.log(f"prompts/{key.removeprefix('observation.prompt.')}", rr.Image(image))
        for key in ("observation.state", "action"):
            if key in item:
                _scalars(rr, key.removeprefix("observation."), item[key], _flat(names[key]))
    rr.disconnect()


def _flat(names) -> list[str] | None:
    if isinstance(names, dict):  # LeRobot writes {"motors": [...]} for some robots
        names = next(iter(names.values()), None)
    return [str(n) for n in names] if isinstance(names, list) else None


def view_attention(cfg: ViewConfig) -> None:
    import av

    from lerobot_condground.core.files import read_json_object
    from lerobot_condground.core.trust import inside

    folder = Path(cfg.attention_dir)
    record = read_json_object(folder / "attention.json", "Attention output")
    if record.get("kind") != "attention":
        raise ValueError(f"{folder / 'attention.json'} is not an output of `condground attention`")
    files = {}
    for field_name in ("video", "maps"):
        rel = record.get(field_name)
        if not isinstance(rel, str) or not inside(folder, rel) or not (folder / rel).is_file():
            raise ValueError(
                f"{folder / 'attention.json'}: {field_name} {rel!r} is not a file inside {folder}"
            )
        files[field_name] = folder / rel
    maps = np.load(files["maps"], allow_pickle=False)
    steps = len(maps)
    per_step = {key: record.get(key) or [] for key in ("stage", "phase_predicted", "phase_probability_place")}
    masses = record.get("attention_mass") or {}
    rr = _start(f"attention/{record.get('policy_label', folder.name)}", cfg.output)
    with av.open(str(files["video"])) as container:
        frames = container.decode(video=0)
        for step in tqdm(range(steps), desc="attention", unit="step", disable=not cfg.progress):
            rr.set_time("frame_index", sequence=step)
            frame = next(frames, None)
            if frame is not None:
                rr.log("attention/overlay", rr.Image(frame.to_ndarray(format="rgb24")))
            rr.log("attention/map", rr.Tensor(maps[step], dim_names=("height", "width")))
            for key, values in per_step.items():
                if step < len(values) and values[step] is not None:
                    rr.log(f"attention/{key}", rr.Scalars([float(values[step])]))
            for key, values in masses.items():
                if step < len(values) and values[step] is not None:
                    rr.log(f"attention/mass/{key}", rr.Scalars([float(values[step])]))
    rr.disconnect()


def _is_recording(path: Path) -> bool:
    with path.open("rb") as f:
        return f.read(4) == RRD_MAGIC


def run_view(cfg: ViewConfig) -> None:
    if cfg.output is not None:
        output = Path(cfg.output)
        if not cfg.output.endswith(".rrd") or output.is_dir():
            raise ValueError(f"--output={cfg.output!r} is not allowed; allowed: a file name ending in .rrd")
        clash = next((p for p in output.parents if p.exists() and not p.is_dir()), None)
        if clash is not None:
            raise ValueError(f"--output={cfg.output!r}: {clash} is a file, not a folder")
        if output.exists() and not _is_recording(output):
            # A rerun recording (an earlier view's) is replaced; anything else there is the user's.
            raise ValueError(
                f"--output={cfg.output!r} exists and is not a rerun recording; allowed: a new file name, or a "
                ".rrd file an earlier view wrote"
            )
    if cfg.attention_dir is not None:
        view_attention(cfg)
    else:
        view_dataset(cfg)
