"""`condground prompts`: label features for a LeRobotDataset recorded on hardware (stock `lerobot-record`).

Reads the dataset, runs a `PromptTracker` (SAM 2, or the color tracker) over one camera of every
chosen episode from one annotation of its first frame, and writes a NEW dataset (the input is never
modified) with the label features the simulation records:

- `observation.prompt.object` / `observation.prompt.receptacle`: positionless (64, 64, 3) crops, cut
  from the annotated first frame and kept for the episode (see `prompt_tracker`), PNG strings;
- `observation.segmentation`: the tracked (H, W) uint8 label map of every frame, PNG string;
- `observation.phase` (1,) int64, from the gripper command in `action` (`phase_from_gripper`).

so that `lerobot-train --policy.type=act_modified` trains on it exactly as on simulated data. The
rewrite is LeRobot's own `dataset_tools.add_features`: videos are copied, not re-encoded, and the
other columns and per-episode statistics are kept as they are (string labels have no statistics).

Prompts: `--object=x,y --receptacle=x,y [--competitors='x,y;x0,y0,x1,y1']` for every episode, or per
episode a JSON file `--annotations=file.json`:
    {"0": {"object": "120,80", "receptacle": "10,20,60,90", "competitors": ["200,40"]}, "3": {...}}
(episodes it does not name use the flags). A click is a point x,y, a box is x0,y0,x1,y1, in pixels of
the camera's frames.
"""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from lerobot_condground.core.configs import DatasetRefConfig, comma_items
from lerobot_condground.core.files import partial_beside
from lerobot_condground.core.labels import (
    OBS_PHASE,
    OBS_PROMPT_OBJECT,
    OBS_PROMPT_RECEPTACLE,
    OBS_SEGMENTATION,
    PNG_FEATURE,
    encode_png,
)
from lerobot_condground.core.provenance import PROMPTS_FILE
from lerobot_condground.labelling.segmenters import (
    SEGMENTERS,
    ColorConfig,
    Prompt,
    Sam2Config,
    make_segmenter,
)

logger = logging.getLogger(__name__)

GRIPPER_NAME = "gripper.pos"


@dataclass
class PromptsConfig:
    # Default repo id: local/ur3e_pickplace.
    dataset: DatasetRefConfig = field(default_factory=DatasetRefConfig)
    # Must not exist yet. Default: <dataset.repo_id>_prompts, in <dataset root>_prompts.
    output: DatasetRefConfig = field(default_factory=DatasetRefConfig)
    # sam2 or color.
    segmenter: str = "sam2"
    # The camera the prompts are given in and the segmentation is computed for.
    camera: str = "observation.images.top"
    # Prompts for every episode (a click x,y or a box x0,y0,x1,y1), unless --annotations names the episode.
    object: str | None = None
    receptacle: str | None = None
    # Competitors (labels 3, 4, ...), separated by semicolons.
    competitors: str = ""
    # JSON file mapping episode index -> {"object": ..., "receptacle": ..., "competitors": [...]}.
    annotations: str | None = None
    # Episodes to label, separated by commas (default: all). The output holds only these.
    episodes: str | None = None
    sam2: Sam2Config = field(default_factory=Sam2Config)
    color: ColorConfig = field(default_factory=ColorConfig)
    # Phase 1 starts once the gripper command (action's gripper.pos) is above threshold for hold_s.
    gripper_threshold: float = 0.5
    gripper_hold_s: float = 0.25
    progress: bool = True

    def __post_init__(self):
        # This command's defaults for the shared groups (see core/configs.py on why not a default_factory).
        self.dataset.repo_id = self.dataset.repo_id or "local/ur3e_pickplace"


# ---------------------------------------------------------------------------------------------- phase
def phase_from_gripper(gripper_command, fps: int, threshold: float = 0.5, hold_s: float = 0.25) -> np.ndarray:
    """(T,) int64 phase labels of one episode from its gripper command (0 open .. 1 closed).

    0 (acquire the object) until the command first closes (> threshold) and stays closed for hold_s
    (round(hold_s * fps) frames, at least 1), 1 (transport and place) from then on, to the episode's
    end (a release and a later re-grasp do not go back to 0). Brief closings (a twitch of the
    teleoperator) do not count. The frames of the closing itself stay 0, as in the simulation, whose
    expert labels its 0.5 s grasp as acquiring: at the default threshold and hold the switch lands
    where the simulation's does (the command crosses 0.5 halfway through the grasp, 0.25 s before its
    end). An episode in which the gripper never closes is all 0 (a warning says so)."""
    closed = np.asarray(gripper_command, dtype=np.float64).reshape(-1) > threshold
    hold = max(1, round(hold_s * fps))
    phase = np.zeros(len(closed), np.int64)
    run = 0
    for t, is_closed in enumerate(closed):
        run = run + 1 if is_closed else 0
        if run == hold:
            phase[t + 1 :] = 1
            return phase
    return phase


def gripper_index(features: dict) -> int:
    """Index of the gripper command in `action`; ValueError when the dataset has none."""
    action = features.get("action")
    if action is None:
        raise ValueError(
            f"The dataset has no 'action' feature; the phase labels need the gripper command "
            f"(action's {GRIPPER_NAME!r}); features: {', '.join(features)}"
        )
    names = action.get("names")
    if isinstance(names, dict):  # older datasets: {"motors": [...]}
        names = next(iter(names.values()), None)
    names = list(names or [])
    for i, name in enumerate(names):
        if name == GRIPPER_NAME or name.endswith("." + GRIPPER_NAME) or name == "gripper":
            return i
    raise ValueError(
        f"The dataset's 'action' has no {GRIPPER_NAME!r} entry for the phase labels; its names: "
        f"{names or '(none)'}; allowed: a dataset recorded with a gripper (0 open .. 1 closed)"
    )


# -------------------------------------------------------------------------------------------- prompts
def _episode_prompts(
    cfg: PromptsConfig, episodes: list[int], height: int, width: int, chosen: bool = False
) -> dict[int, dict]:
    """{episode: {"object": Prompt, "receptacle": Prompt, "competitors": [Prompt]}}, validated against
    the frame size before any model is loaded."""
    default = None
    if cfg.object is not None or cfg.receptacle is not None:
        if cfg.object is None or cfg.receptacle is None:
            raise ValueError("Give both --object and --receptacle (or neither, with --annotations)")
        default = {
            "object": cfg.object,
            "receptacle": cfg.receptacle,
            "competitors": [c for c in cfg.competitors.split(";") if c.strip()],
        }
    per_episode: dict[int, dict] = {}
    if cfg.annotations:
        path = Path(cfg.annotations)
        if not path.is_file():
            raise FileNotFoundError(f"--annotations={path}: no such file")
        try:
            raw = json.loads(path.read_text())
            per_episode = {int(k): v for k, v in raw.items()}
        except (json.JSONDecodeError, AttributeError, TypeError, ValueError) as err:
            raise ValueError(
                f"--annotations={path} is not a JSON object of episode index -> prompts ({err})"
            ) from None
        stray = sorted(set(per_episode) - set(episodes))
        if stray:
            where = "in --episodes" if chosen else "in the dataset"
            raise ValueError(
                f"--annotations names episodes {stray} that are not {where}; allowed: {_ranges(episodes)}"
            )
    elif default is None:
        raise ValueError("No prompts: give --object=x,y --receptacle=x,y, or --annotations=file.json")
    missing = [ep for ep in episodes if ep not in per_episode and default is None]
    if missing:
        raise ValueError(
            f"Episodes {_ranges(missing)} have no prompts in --annotations and there are no "
            f"--object/--receptacle flags for them"
        )
    out = {}
    for ep in episodes:
        entry = per_episode.get(ep, default)
        if not isinstance(entry, dict) or "object" not in entry or "receptacle" not in entry:
            raise ValueError(f"Prompts of episode {ep} need 'object' and 'receptacle'; got {entry!r}")
        competitors = entry.get("competitors", [])
        if isinstance(competitors, str):
            competitors = [c for c in competitors.split(";") if c.strip()]
        prompts = {
            "object": Prompt.parse(entry["object"]),
            "receptacle": Prompt.parse(entry["receptacle"]),
            "competitors": [Prompt.parse(c) for c in competitors],
        }
        for role, value in prompts.items():
            for p in value if role == "competitors" else [value]:
                try:
                    p.check_inside(height, width)
                except ValueError as err:
                    raise ValueError(f"Episode {ep}, {role} prompt: {err}") from None
        out[ep] = prompts
    return out


def _ranges(indices) -> str:
    indices = sorted(indices)
    if not indices:
        return "(none)"
    parts, start = [], indices[0]
    for a, b in zip(indices, indices[1:] + [None]):
        if b != a + 1:
            parts.append(str(start) if start == a else f"{start}-{a}")
            start = b
    return ", ".join(parts)


def _parse_episodes(text: str | None, total: int) -> list[int]:
    if text is None or not str(text).strip():
        return list(range(total))
    try:
        chosen = sorted({int(p) for p in comma_items(str(text).strip().strip("[]"), "--episodes")})
    except ValueError:
        raise ValueError(
            f"--episodes={text!r} is not a list of episode indices; allowed: e.g. --episodes=0,2,5"
        ) from None
    outside = [ep for ep in chosen if not 0 <= ep < total]
    if outside or not chosen:
        raise ValueError(
            f"--episodes={text!r}: episodes {outside or '(none)'} are not in the dataset; allowed: "
            f"0..{total - 1}"
        )
    return chosen


# -------------------------------------------------------------------------------------------- dataset
def _to_uint8_hwc(image) -> np.ndarray:
    import torch

    image = image if isinstance(image, torch.Tensor) else torch.as_tensor(np.asarray(image))
    if (
        image.dtype != torch.uint8
    ):  # LeRobot hands out float CHW in [0, 1] (video frames with return_uint8: uint8)
        image = (image * 255).round().clamp(0, 255).to(torch.uint8)
    return image.permute(1, 2, 0).numpy() if image.shape[0] == 3 else image.numpy()


def label_dataset(cfg: PromptsConfig) -> dict:
    """Writes the labelled copy; returns counts for the summary."""
    from lerobot.datasets.dataset_tools import add_features, delete_episodes
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from tqdm import tqdm

    from lerobot_condground.labelling.prompt_tracker import PromptTracker

    if cfg.segmenter not in SEGMENTERS:
        raise ValueError(f"Unknown --segmenter={cfg.segmenter!r}; allowed: {', '.join(SEGMENTERS)}")
    src_root = cfg.dataset.path()
    if not (src_root / "meta" / "info.json").is_file():
        raise FileNotFoundError(
            f"--dataset.root={src_root} holds no LeRobotDataset (no meta/info.json); allowed: "
            f"the root of a local dataset, e.g. one written by lerobot-record"
        )
    out_repo = cfg.output.repo_id or f"{cfg.dataset.repo_id}_prompts"
    out_root = Path(cfg.output.root) if cfg.output.root else src_root.with_name(src_root.name + "_prompts")
    if out_root.exists():
        raise FileExistsError(
            f"--output.root={out_root} already exists; allowed: a path that does not exist yet "
            f"(the labelled copy is always written fresh, the input is never modified)"
        )
    source = LeRobotDataset(cfg.dataset.repo_id, root=src_root, return_uint8=True)
    meta = source.meta
    if cfg.camera not in meta.camera_keys:
        raise ValueError(
            f"--camera={cfg.camera!r} is not a camera of {src_root}; allowed: "
            f"{', '.join(meta.camera_keys) or '(the dataset has no camera)'}"
        )
    present = [
        key
        for key in (OBS_SEGMENTATION, OBS_PHASE, OBS_PROMPT_OBJECT, OBS_PROMPT_RECEPTACLE)
        if key in meta.features
    ]
    if present:
        raise ValueError(
            f"{src_root} already has label features {present}; allowed: a dataset without them "
            f"(recorded on hardware, or by `condground record --dataset.labels=false`)"
        )
    grip = gripper_index(meta.features)
    height, width = meta.features[cfg.camera]["shape"][:2]
    episodes = _parse_episodes(cfg.episodes, meta.total_episodes)
    prompts = _episode_prompts(cfg, episodes, height, width, chosen=bool(cfg.episodes))
    # SAM 2 is loaded (or fails to) only after every input was checked.
    segmenter = make_segmenter(cfg.segmenter, **asdict(cfg.sam2 if cfg.segmenter == "sam2" else cfg.color))
    tracker = PromptTracker(segmenter)

    segmentation, crops_object, crops_receptacle, phases = [], [], [], []
    track_seconds, frames = 0.0, 0
    spans = [
        (int(meta.episodes[ep]["dataset_from_index"]), int(meta.episodes[ep]["dataset_to_index"]))
        for ep in episodes
    ]
    actions = source.hf_dataset.with_format("numpy")["action"]
    bar = tqdm(
        total=sum(b - a for a, b in spans),
        desc=f"prompts {cfg.segmenter} {cfg.dataset.repo_id}",
        unit="frame",
        disable=not cfg.progress,
    )
    try:
        for ep, (start, stop) in zip(episodes, spans):
            p = prompts[ep]
            phase = phase_from_gripper(
                np.stack(actions[start:stop])[:, grip], meta.fps, cfg.gripper_threshold, cfg.gripper_hold_s
            )
            if not phase.any():
                logger.warning(
                    "Episode %d: the gripper command never stays closed; its phase is 0 throughout", ep
                )
            for i in range(start, stop):
                frame = _to_uint8_hwc(source[i][cfg.camera])
                t0 = time.perf_counter()
                if i == start:
                    result = tracker.start(frame, p["object"], p["receptacle"], p["competitors"])
                    # One PNG per episode for the crops: they are the same on all its frames.
                    obj_png, rec_png = encode_png(result.object_crop), encode_png(result.receptacle_crop)
                else:
                    result = tracker.track(frame)
                track_seconds += time.perf_counter() - t0
                segmentation.append(encode_png(result.labels))
                crops_object.append(obj_png)
                crops_receptacle.append(rec_png)
                frames += 1
                bar.update(1)
            phases.append(phase)
    finally:
        bar.close()

    work = None
    partial = partial_beside(out_root)
    out_root.parent.mkdir(parents=True, exist_ok=True)
    try:
        if len(episodes) < meta.total_episodes:
            # add_features writes every frame of its input: drop the other episodes first (LeRobot's
            # delete_episodes, into a scratch directory beside the output).
            out_root.parent.mkdir(parents=True, exist_ok=True)
            work = Path(tempfile.mkdtemp(prefix=out_root.name + ".", dir=out_root.parent))
            others = [ep for ep in range(meta.total_episodes) if ep not in set(episodes)]
            source = delete_episodes(source, others, output_dir=work / "subset", repo_id=out_repo)
        add_features(
            source,
            {
                OBS_PROMPT_OBJECT: (np.array(crops_object, dtype=object), dict(PNG_FEATURE)),
                OBS_PROMPT_RECEPTACLE: (np.array(crops_receptacle, dtype=object), dict(PNG_FEATURE)),
                OBS_SEGMENTATION: (np.array(segmentation, dtype=object), dict(PNG_FEATURE)),
                OBS_PHASE: (
                    np.concatenate(phases).reshape(-1, 1),
                    {"dtype": "int64", "shape": (1,), "names": ["phase"]},
                ),
            },
            output_dir=partial,
            repo_id=out_repo,
        )
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
    (partial / PROMPTS_FILE).write_text(
        json.dumps(
            {
                "source": {"repo_id": cfg.dataset.repo_id, "root": str(src_root)},
                "source_episodes": episodes,
                "camera": cfg.camera,
                "segmenter": cfg.segmenter,
                "segmenter_config": asdict(cfg.sam2) if cfg.segmenter == "sam2" else asdict(cfg.color),
                "prompts": {
                    str(ep): {
                        "object": str(p["object"]),
                        "receptacle": str(p["receptacle"]),
                        "competitors": [str(c) for c in p["competitors"]],
                    }
                    for ep, p in prompts.items()
                },
                "phase": {"gripper_threshold": cfg.gripper_threshold, "gripper_hold_s": cfg.gripper_hold_s},
            },
            indent=1,
        )
    )
    partial.rename(out_root)  # only a whole copy takes the output's name: a failed run never blocks the rerun
    return {
        "episodes": len(episodes),
        "frames": frames,
        "root": str(out_root),
        "repo_id": out_repo,
        "ms_per_frame": 1000 * track_seconds / max(frames, 1),
        "phase1_share": float(np.concatenate(phases).mean()) if phases else 0.0,
    }


def format_summary(result: dict) -> str:
    return (
        f"labelled {result['episodes']} episodes, {result['frames']} frames -> {result['repo_id']} at "
        f"{result['root']}\ntracking {result['ms_per_frame']:.1f} ms/frame; phase 1 on "
        f"{result['phase1_share']:.0%} of frames"
    )


def click_on(labels: np.ndarray, label: int) -> str:
    """The click a user would give an entity of a label map: its pixel nearest the entity's centroid."""
    ys, xs = np.nonzero(labels == label)
    k = int(((ys - ys.mean()) ** 2 + (xs - xs.mean()) ** 2).argmin())
    return f"{xs[k]},{ys[k]}"
