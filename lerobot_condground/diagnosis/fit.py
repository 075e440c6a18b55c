"""`condground fit`: how precisely a checkpoint reproduces demonstrations, in physical units.

Teacher-forced: every frame of the chosen episodes goes through the checkpoint's own pre-processor (as at
evaluation: no gradients, so no copy-paste; dropout off) and one action-chunk prediction. The first
`--fit.steps` actions of each chunk (default: the checkpoint's n_action_steps, what a rollout executes) are
compared with the demonstrated ones: the absolute error of each joint target (rad) and of the gripper
command, and the distance between the tool-centre points the two joint targets put the gripper at (cm,
the UR3e's forward kinematics). `l1` is the training loss's term on the whole chunk (normalized units).
Beside the errors, per frame: the share of the supervised cross-attention head's weight (act_modified's
`attention_head` of the last decoder layer; head 0 for stock ACT) that falls on its camera's tokens before
the paper's renormalization (a head that puts its weight on the 1D tokens satisfies eq. (1)'s terms through a
camera share near zero), and, for a policy with a phase head, the phase it predicts (at inference that picks
the prompt crop).

Frames are grouped by segment, read off the demonstration: the dataset's phase (0 acquire, 1 place) and
what the demonstrated gripper command does over the compared steps (open throughout, closing, closed
throughout, opening): reach, grasp, lift, carry, release, retreat. The grasp segment is where a
centimetre decides whether the fingers close on the cube.

Run it on the recording a checkpoint was trained on (how well it fits) and on a held-out recording of
the same task (how well that generalizes). Writes `fit.json` (per segment and overall) and
`frames.parquet` (one row per frame, enough to recompute every number).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lerobot_condground.core.configs import DatasetRefConfig, PolicyRefConfig
from lerobot_condground.core.provenance import command_line, versions
from lerobot_condground.core.ur3e import forward_kinematics
from lerobot_condground.diagnosis.hooks import ACTProbe, acting_model, camera_attention, resolve_target

logger = logging.getLogger(__name__)

SEGMENTS = ("reach", "grasp", "lift", "carry", "release", "retreat")
# "The head looks past the camera": less than 1 % of its weight on the camera's tokens.
LOW_CAMERA_SHARE = 0.01
# (phase, what the gripper command does over the compared steps) -> segment
_SEGMENT_OF = {
    (0, "open"): "reach",
    (0, "closing"): "grasp",
    (0, "closed"): "lift",
    (0, "opening"): "grasp",  # a re-grasp in a demonstration: still acquiring
    (1, "closed"): "carry",
    (1, "opening"): "release",
    (1, "open"): "retreat",
    (1, "closing"): "carry",
}
N_JOINTS = 6
GRIPPER_CLOSED = 0.5  # action[6]: 0 open .. 1 closed


@dataclass
class FitOptions:
    # Episodes of the dataset: "all", a range "a:b" (b excluded) or indices "0,3,7".
    episodes: str = "all"
    # Actions of each chunk compared (default: the checkpoint's n_action_steps).
    steps: int | None = None
    # Every k-th frame of each episode.
    frame_stride: int = 1
    batch_size: int = 32


@dataclass
class FitConfig:
    policy: PolicyRefConfig = field(default_factory=PolicyRefConfig)
    dataset: DatasetRefConfig = field(default_factory=DatasetRefConfig)
    fit: FitOptions = field(default_factory=FitOptions)
    output_dir: str = "outputs/fit"
    progress: bool = True


def parse_episodes(text: str, total: int) -> list[int]:
    """Episode indices named by --fit.episodes, each checked against the dataset's count."""
    text = text.strip()
    allowed = f"allowed: all, a range a:b or indices separated by commas, within 0..{total - 1}"
    try:
        if text == "all":
            episodes = list(range(total))
        elif ":" in text:
            start, stop = (int(v) for v in text.split(":"))
            episodes = list(range(start, stop))
        else:
            episodes = [int(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--fit.episodes={text!r} is not allowed; {allowed}") from None
    if not episodes or min(episodes) < 0 or max(episodes) >= total or len(set(episodes)) != len(episodes):
        raise ValueError(f"--fit.episodes={text!r} names no episode, or one outside the dataset; {allowed}")
    return episodes


def gripper_pattern(command: np.ndarray) -> np.ndarray:
    """open / closing / closed / opening for each row of demonstrated gripper commands (frames, steps)."""
    closed = command >= GRIPPER_CLOSED
    first, last = closed[:, 0], closed[:, -1]
    return np.where(
        first & last, "closed", np.where(~first & ~last, "open", np.where(last, "closing", "opening"))
    )


def segments(phase: np.ndarray, demonstrated: np.ndarray) -> np.ndarray:
    """The segment of each frame: its phase and what the demonstrated gripper command does."""
    pattern = gripper_pattern(demonstrated[..., N_JOINTS])
    return np.array([_SEGMENT_OF[(int(p), g)] for p, g in zip(phase, pattern, strict=True)], dtype=object)


def frame_errors(predicted: np.ndarray, demonstrated: np.ndarray, valid: np.ndarray) -> dict[str, np.ndarray]:
    """Per-frame mean errors over the valid compared steps; arrays (frames, steps, 7) in physical units."""
    weight = valid.astype(float)
    count = weight.sum(1).clip(min=1)

    def mean(x):  # (frames, steps) -> (frames,)
        return (x * weight).sum(1) / count

    joints = np.abs(predicted[..., :N_JOINTS] - demonstrated[..., :N_JOINTS])
    tcp = np.linalg.norm(
        forward_kinematics(predicted[..., :N_JOINTS])[0]
        - forward_kinematics(demonstrated[..., :N_JOINTS])[0],
        axis=-1,
    )
    out = {f"joint{j}_rad": mean(joints[..., j]) for j in range(N_JOINTS)}
    out["gripper"] = mean(np.abs(predicted[..., N_JOINTS] - demonstrated[..., N_JOINTS]))
    out["tcp_cm"] = mean(tcp) * 100
    return out


def summarize(frames) -> dict:
    """Mean errors of a frame table (pandas), per segment and over all frames."""

    def one(group) -> dict:
        return {
            "frames": len(group),
            "l1": float(group["l1"].mean()),
            "joint_rad": [float(group[f"joint{j}_rad"].mean()) for j in range(N_JOINTS)],
            "gripper": float(group["gripper"].mean()),
            "tcp_cm": float(group["tcp_cm"].mean()),
            "tcp_cm_median": float(group["tcp_cm"].median()),
            "tcp_cm_p90": float(group["tcp_cm"].quantile(0.9)),
            "head_camera_share_median": float(group["head_camera_share"].median()),
            "head_camera_share_low": float((group["head_camera_share"] < LOW_CAMERA_SHARE).mean()),
            "phase_accuracy": (
                None
                if group["phase_predicted"].isna().all()
                else float((group["phase_predicted"] == group["phase"]).mean())
            ),
        }

    by_segment = {s: one(g) for s, g in frames.groupby("segment") if len(g)}
    return {"all": one(frames), **{s: by_segment[s] for s in SEGMENTS if s in by_segment}}


def format_fit(result: dict) -> str:
    lines = [
        f"{'segment':<8} {'frames':>6} {'l1':>7} {'tcp cm':>7} {'p90 cm':>7} {'base rad':>8} {'wrist3 rad':>10} "
        f"{'gripper':>7} {'cam share':>9} {'<1 %':>5} {'phase acc':>9}"
    ]
    for name, row in result["segments"].items():
        accuracy = "n/a" if row["phase_accuracy"] is None else f"{row['phase_accuracy']:.3f}"
        lines.append(
            f"{name:<8} {row['frames']:>6} {row['l1']:>7.4f} {row['tcp_cm']:>7.2f} {row['tcp_cm_p90']:>7.2f} "
            f"{row['joint_rad'][0]:>8.4f} {row['joint_rad'][5]:>10.4f} {row['gripper']:>7.3f} "
            f"{row['head_camera_share_median']:>9.2g} {row['head_camera_share_low']:>5.2f} {accuracy:>9}"
        )
    return "\n".join(lines)


def _load(cfg: FitConfig):
    """(policy, preprocessor, postprocessor, dataset, described checkpoint, episodes, steps compared), checked."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    from lerobot_condground.diagnosis.hooks import check_act_family
    from lerobot_condground.evaluation.checkpoints import describe_checkpoint, resolve_device

    opts = cfg.fit
    if opts.batch_size < 1:
        raise ValueError(f"--fit.batch_size={opts.batch_size} must be at least 1")
    if opts.frame_stride < 1:
        raise ValueError(f"--fit.frame_stride={opts.frame_stride} must be at least 1")
    path = cfg.policy.single()
    described = describe_checkpoint(path, cfg.policy.label, trust_remote_code=cfg.policy.trust_remote_code)
    check_act_family(described)
    policy_cfg = PreTrainedConfig.from_pretrained(described.local)
    steps = policy_cfg.n_action_steps if opts.steps is None else opts.steps
    if not 1 <= steps <= policy_cfg.chunk_size:
        raise ValueError(
            f"--fit.steps={opts.steps} is not allowed; allowed: 1 to the checkpoint's chunk_size "
            f"({policy_cfg.chunk_size})"
        )
    root = cfg.dataset.path()
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(f"--dataset.root={str(root)!r} is not a LeRobotDataset (no meta/info.json)")
    meta = LeRobotDatasetMetadata(cfg.dataset.repo_id or root.name, root=root)
    episodes = parse_episodes(opts.episodes, meta.total_episodes)
    missing = [k for k in ("action", "observation.phase") if k not in meta.features]
    if missing:
        raise ValueError(
            f"Dataset {root} has no {', '.join(missing)}; `condground fit` needs demonstrated actions and the "
            "phase labels condground record writes"
        )
    wanted = {**policy_cfg.input_features, **policy_cfg.output_features}
    lacking = [k for k in wanted if k not in meta.features]
    if lacking:
        raise ValueError(f"Dataset {root} lacks {', '.join(lacking)}, which checkpoint {path} reads")
    device = resolve_device(cfg.policy.device)
    policy_cfg.pretrained_path = Path(described.local)
    policy_cfg.device = device
    policy = get_policy_class(policy_cfg.type).from_pretrained(described.local, config=policy_cfg)
    policy.eval()
    preprocessor, postprocessor = make_pre_post_processors(
        policy_cfg=policy_cfg,
        pretrained_path=described.local,
        preprocessor_overrides={"device_processor": {"device": device}},
    )
    dataset = LeRobotDataset(
        cfg.dataset.repo_id or root.name,
        root=root,
        episodes=episodes,
        delta_timestamps=resolve_delta_timestamps(policy_cfg, meta),
    )
    return policy, preprocessor, postprocessor, dataset, described, episodes, steps


def _batch_rows(policy, preprocessor, postprocessor, dataset, indices: list[int], steps: int, probe, target):
    """One batch of dataset frames -> its rows of the frame table."""
    import pandas as pd
    import torch

    batch = torch.utils.data.default_collate([dataset[i] for i in indices])
    demonstrated = batch["action"].numpy().astype(float)[:, :steps]
    valid = ~batch["action_is_pad"].numpy()[:, :steps]
    phase = batch["observation.phase"].reshape(-1).numpy()
    processed = preprocessor(batch)
    with probe:  # the forward predict_action_chunk runs, with the supervised head's query and key captured
        outputs = probe.forward(policy, processed)
    predicted = outputs[0]
    _, share = camera_attention(probe, target)
    aux = outputs[2] if len(outputs) > 2 and isinstance(outputs[2], dict) else {}
    phase_predicted = (
        aux["phase_logits"].argmax(-1).float().cpu().numpy()
        if "phase_logits" in aux
        else np.full(len(indices), np.nan)
    )
    chunk_valid = ~processed["action_is_pad"].unsqueeze(-1)
    l1 = (torch.abs(processed["action"] - predicted) * chunk_valid).sum((1, 2)) / (
        chunk_valid.sum((1, 2)) * predicted.shape[-1]
    ).clamp_min(1)
    predicted = postprocessor(predicted).float().cpu().numpy().astype(float)[:, :steps]
    return pd.DataFrame(
        {
            "episode": batch["episode_index"].reshape(-1).numpy(),
            "frame_index": batch["frame_index"].reshape(-1).numpy(),
            "phase": phase,
            "segment": segments(phase, demonstrated),
            "l1": l1.float().cpu().numpy(),
            **frame_errors(predicted, demonstrated, valid),
            "head_camera_share": share,
            "phase_predicted": phase_predicted,
        }
    )


def run_fit(cfg: FitConfig) -> Path:
    """Teacher-forced errors of one ACT-family checkpoint on a dataset -> DIR/fit.json, DIR/frames.parquet."""
    import pandas as pd
    import torch
    from tqdm import tqdm

    policy, preprocessor, postprocessor, dataset, described, episodes, steps = _load(cfg)
    target = resolve_target(policy.config)
    probe = ACTProbe(acting_model(policy), attention_layer=target.layer)
    out = Path(cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    frame_index = np.asarray(dataset.hf_dataset["frame_index"]).reshape(-1)
    indices = np.flatnonzero(frame_index % cfg.fit.frame_stride == 0).tolist()
    logger.info(
        "fit %s (%s): %d frames of %d episodes", described.label, described.hash, len(indices), len(episodes)
    )
    rows = []
    batches = range(0, len(indices), cfg.fit.batch_size)
    for start in tqdm(batches, desc="fit", unit="batch", disable=not cfg.progress):
        with torch.inference_mode():  # no gradients: the copy-paste step stays off, as at evaluation
            rows.append(
                _batch_rows(
                    policy,
                    preprocessor,
                    postprocessor,
                    dataset,
                    indices[start : start + cfg.fit.batch_size],
                    steps,
                    probe,
                    target,
                )
            )
    frames = pd.concat(rows, ignore_index=True)
    frames.to_parquet(out / "frames.parquet", index=False)
    result = {
        "checkpoint": described.path,
        "checkpoint_hash": described.hash,
        "label": described.label,
        "dataset": str(cfg.dataset.path()),
        "episodes": episodes,
        "steps": steps,
        "attention": {"head": target.head, "layer": target.layer, "camera": target.camera},
        "frame_stride": cfg.fit.frame_stride,
        "segments": summarize(frames),
        "command": command_line("fit", cfg),
        "versions": versions(),
    }
    (out / "fit.json").write_text(json.dumps(result, indent=2))
    print(format_fit(result))  # noqa: T201 (the command's result)
    return out
