"""`condground attention`: where one cross-attention head of an ACT-family policy looks, step by step.

One closed-loop episode of the policy: the executed actions come from its normal `select_action`
(ACT's action queue untouched, exactly as in lerobot-eval). ACT runs its model once per chunk, so
at every step one extra forward pass (inference mode, z = 0) on the current observation captures
the chosen head's cross-attention (`--attention.head`, default the supervised head of act_modified,
0 for stock ACT; `--attention.layer`, default the last decoder layer) with a forward pre-hook on
that layer's nn.MultiheadAttention. The head's softmax (before dropout) is averaged over the
action queries and kept on the chosen camera's token grid, renormalized to sum 1 there, upsampled
to the frame and blended over it as a heat map, with the predicted phase (act_modified's phase
head) and the stage reached written on the frame.

Writes `attention.mp4` (libx264, else mpeg4), `stills/step_XXXX.png` (first frame, phase and stage
changes, last frame), `attention_maps.npy` (steps, h, w) and `attention.json` with per step the
predicted phase, the stage, and the attention mass on the target object, the target receptacle and
the competitors (the env's segmentation pooled to the token grid: the fraction of each token's
pixels showing the entity, weighted by the token's attention).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lerobot_condground.core.configs import EvalEnvConfig, PolicyRefConfig
from lerobot_condground.core.provenance import command_line, versions
from lerobot_condground.diagnosis.hooks import (
    ACTProbe,
    acting_model,
    camera_attention,
    load_act_family,
    resolve_target,
)

logger = logging.getLogger(__name__)

PHASE_NAMES = ("pick", "place")
STAGE_NAMES = ("none", "pick", "lift", "place")
CODECS = ("libx264", "mpeg4")
MASS_KEYS = ("target_object", "target_receptacle", "competitors")
MAX_CHANGE_STILLS = 4


@dataclass
class AttentionOptions:
    # Layout seed of the episode (what env.reset(seed=) gets).
    seed: int = 0
    # Cross-attention head; default: act_modified's supervised `attention_head`, 0 for stock ACT.
    head: int | None = None
    # Decoder layer (negative counts from the end); default: the last one.
    layer: int = -1
    # Camera whose token grid is shown; default: act_modified's `attention_camera`, else the first camera.
    camera: str | None = None
    # Heat map opacity over the frame.
    alpha: float = 0.45
    # Video codec: libx264 (default) or mpeg4; falls back to the other when this PyAV cannot encode it.
    codec: str = "libx264"


@dataclass
class AttentionConfig:
    policy: PolicyRefConfig = field(default_factory=PolicyRefConfig)
    # --env.condition: the scene of the episode (default full_mixed).
    env: EvalEnvConfig = field(default_factory=EvalEnvConfig)
    attention: AttentionOptions = field(default_factory=AttentionOptions)
    output_dir: str = "outputs/attention"
    progress: bool = True

    def __post_init__(self):
        # This command's defaults for the shared groups (see core/configs.py on why not a default_factory).
        self.env.condition = self.env.condition or "full_mixed"


def attention_masses(attention: np.ndarray, segmentation: np.ndarray) -> dict[str, float]:
    """Attention mass (h, w grid summing to 1) on the target object (label 1), target receptacle (2) and
    competitors (>= 3, 255 included) of a (H, W) label map: each token's attention spread evenly over
    its pixels."""
    import cv2

    h, w = attention.shape
    masks = {
        "target_object": segmentation == 1,
        "target_receptacle": segmentation == 2,
        "competitors": segmentation >= 3,
    }
    out = {}
    for name, mask in masks.items():
        coverage = cv2.resize(mask.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
        out[name] = float((attention * coverage).sum())
    return out


# ---------------------------------------------------------------------------------------------- drawing
def overlay(frame: np.ndarray, attention: np.ndarray, alpha: float, lines: tuple[str, str]) -> np.ndarray:
    """RGB frame with the attention grid upsampled, colour-mapped (JET, scaled to its max) and blended,
    and two text lines (top left, bottom left)."""
    import cv2

    height, width = frame.shape[:2]
    heat = cv2.resize(attention.astype(np.float32), (width, height), interpolation=cv2.INTER_LINEAR)
    heat = np.clip(heat / max(float(heat.max()), 1e-12), 0.0, 1.0)
    colored = cv2.cvtColor(
        cv2.applyColorMap((heat * 255).astype(np.uint8), cv2.COLORMAP_JET), cv2.COLOR_BGR2RGB
    )
    out = cv2.addWeighted(frame, 1.0 - alpha, colored, alpha, 0.0)
    scale = max(0.28, 0.45 * width / 320)
    thickness = 1
    (_, text_h), baseline = cv2.getTextSize("Ag", cv2.FONT_HERSHEY_SIMPLEX, scale, thickness)
    for text, y in ((lines[0], text_h + 2), (lines[1], height - baseline - 1)):
        cv2.putText(out, text, (2, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), thickness + 2, cv2.LINE_AA)
        cv2.putText(
            out, text, (2, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), thickness, cv2.LINE_AA
        )
    return out


def pick_codec(preferred: str) -> str:
    import av

    if preferred not in CODECS:
        raise ValueError(f"--attention.codec={preferred!r} is not supported; allowed: {', '.join(CODECS)}")
    available = av.codecs_available
    for codec in (preferred, *[c for c in CODECS if c != preferred]):
        if codec in available:
            if codec != preferred:
                logger.warning(
                    "This PyAV cannot encode %s; writing the video with %s instead", preferred, codec
                )
            return codec
    raise RuntimeError(
        f"This PyAV ({av.__version__}) can encode none of {', '.join(CODECS)}; no video written"
    )


class VideoWriter:
    """RGB frames -> mp4 with PyAV (yuv420p; odd sizes are padded by one pixel, which yuv420p needs)."""

    def __init__(self, path: Path, fps: int, codec: str):
        self.path, self.fps, self.codec = path, fps, codec
        self.container = None
        self.stream = None

    def write(self, rgb: np.ndarray) -> None:
        import av

        height, width = rgb.shape[:2]
        pad_h, pad_w = height % 2, width % 2
        if pad_h or pad_w:
            rgb = np.pad(rgb, ((0, pad_h), (0, pad_w), (0, 0)), mode="edge")
        if self.container is None:
            av.logging.set_level(av.logging.ERROR)  # x264 prints its settings and statistics otherwise
            self.container = av.open(str(self.path), mode="w")
            options = {"crf": "18", "preset": "veryfast"} if self.codec == "libx264" else {}
            self.stream = self.container.add_stream(self.codec, rate=self.fps, options=options)
            self.stream.width, self.stream.height = rgb.shape[1], rgb.shape[0]
            self.stream.pix_fmt = "yuv420p"
            if self.codec == "mpeg4":
                self.stream.bit_rate = 4_000_000
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        for packet in self.stream.encode(frame):
            self.container.mux(packet)

    def close(self) -> None:
        if self.container is None:
            return
        for packet in self.stream.encode():
            self.container.mux(packet)
        self.container.close()
        self.container = None


def save_png(path: Path, rgb: np.ndarray) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def json_safe(row: dict) -> dict:
    """An outcome row with NaN (no competitor grasped) as null, so the JSON stays strict."""
    return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in row.items()}


# ---------------------------------------------------------------------------------------------- command
def run_attention(cfg: AttentionConfig) -> Path:
    """One closed-loop episode with the per-step attention overlay -> DIR/attention.json, .mp4, stills."""
    import torch
    from tqdm import tqdm

    from lerobot_condground.evaluation.rollout import run_episodes

    opts = cfg.attention
    if not 0.0 <= opts.alpha <= 1.0:
        raise ValueError(f"--attention.alpha={opts.alpha} must be in [0, 1]")
    codec = pick_codec(opts.codec)
    loaded, spec = load_act_family(cfg.policy, cfg.env)
    policy = loaded.policy
    target = resolve_target(policy.config, opts.head, opts.layer, opts.camera)
    model = acting_model(policy)
    has_phase_head = hasattr(model, "phase_head")

    out = Path(cfg.output_dir)
    (out / "stills").mkdir(parents=True, exist_ok=True)
    # An earlier run's JSON would describe this run's files if it stopped before writing its own.
    (out / "attention.json").unlink(missing_ok=True)
    for old in (out / "stills").glob("step_*.png"):
        old.unlink()
    video = VideoWriter(out / "attention.mp4", spec.fps, codec)
    env = spec.make()
    probe = ACTProbe(model, attention_layer=target.layer)
    model_calls = [0]
    counter = model.register_forward_hook(lambda *_: model_calls.__setitem__(0, model_calls[0] + 1))
    record = {
        "phase": [],
        "phase_probability": [],
        "stage": [],
        "camera_share": [],
        **{key: [] for key in MASS_KEYS},
    }
    maps: list[np.ndarray] = []
    stills: list[int] = []
    last = {"frame": None, "phase": None, "stage": None, "changes": 0}
    bar = tqdm(total=spec.episode_length, desc="attention", unit="step", disable=not cfg.progress)

    def on_step(step: int, batch: dict, observations: list[dict], active: np.ndarray) -> None:
        with torch.inference_mode(), probe:
            outputs = probe.forward(policy, batch)
            attention, share = camera_attention(probe, target)
        aux = outputs[2] if len(outputs) > 2 and isinstance(outputs[2], dict) else {}
        phase = probability = None
        if has_phase_head and "phase_logits" in aux:
            probs = aux["phase_logits"].float().softmax(-1)[0]
            phase, probability = int(probs.argmax()), float(probs[1])
        stage = int(env.tracker.stage)
        frame = observations[0]["pixels"][target.camera]
        masses = attention_masses(attention[0], env.render_segmentation(target.camera))
        maps.append(attention[0].astype(np.float32))
        record["phase"].append(phase)
        record["phase_probability"].append(probability)
        record["stage"].append(stage)
        record["camera_share"].append(float(share[0]))
        for key in MASS_KEYS:
            record[key].append(masses[key])
        phase_text = (
            "phase: n/a"
            if phase is None
            else f"phase: {PHASE_NAMES[phase]} {max(probability, 1 - probability):.2f}"
        )
        composed = overlay(
            frame,
            attention[0],
            opts.alpha,
            (f"t={step} h{target.head} {phase_text}", f"stage: {STAGE_NAMES[stage]}"),
        )
        video.write(composed)
        changed = step > 0 and (phase != last["phase"] or stage != last["stage"])
        if step == 0 or (changed and last["changes"] < MAX_CHANGE_STILLS):
            save_png(out / "stills" / f"step_{step:04d}.png", composed)
            stills.append(step)
            last["changes"] += int(changed)
        last.update(frame=composed, phase=phase, stage=stage, step=step)
        bar.update(1)

    try:
        outcome = run_episodes(loaded, [env], [opts.seed], max_steps=spec.episode_length, on_step=on_step)[0]
    finally:
        bar.close()
        counter.remove()
        video.close()
        env.close()
    frames = len(maps)
    if frames and stills[-1] != frames - 1:
        save_png(out / "stills" / f"step_{frames - 1:04d}.png", last["frame"])
        stills.append(frames - 1)
    np.save(out / "attention_maps.npy", np.stack(maps) if maps else np.zeros((0, 0, 0), np.float32))

    grid = list(maps[0].shape) if maps else None
    masses = {key: record[key] for key in MASS_KEYS}
    result = {
        "kind": "attention",
        "policy_label": loaded.label,
        "checkpoint": loaded.path,
        "checkpoint_hash": loaded.hash,
        "policy_type": loaded.policy_type,
        "variant": loaded.variant,
        "task": spec.task,
        "condition": spec.condition,
        "counterbalanced": spec.counterbalanced,
        "servo": spec.servo,
        "seed": opts.seed,
        "head": target.head,
        "layer": target.layer,
        "camera": target.camera,
        "grid": grid,
        "observation_height": spec.observation_height,
        "observation_width": spec.observation_width,
        "frames": frames,
        "fps": spec.fps,
        "video": "attention.mp4",
        "codec": codec,
        "stills": [f"stills/step_{s:04d}.png" for s in stills],
        "maps": "attention_maps.npy",
        "phase_predicted": record["phase"],
        "phase_probability_place": record["phase_probability"],
        "stage": record["stage"],
        "attention_mass": masses,
        "attention_mass_mean": {key: float(np.mean(v)) if v else None for key, v in masses.items()},
        "camera_share": record["camera_share"],
        "forward_passes": probe.forward_passes,
        "chunk_forward_passes": model_calls[0] - probe.forward_passes,
        "outcome": json_safe(outcome),
        "command": command_line("attention", cfg),
        "versions": versions(),
    }
    (out / "attention.json").write_text(json.dumps(result, indent=2, allow_nan=False))
    mean = result["attention_mass_mean"]
    print(
        f"{loaded.label} {spec.task} {spec.condition} seed {opts.seed}: {frames} steps, stage "
        f"{STAGE_NAMES[outcome['stage']]}; head {target.head} of decoder layer {target.layer} on {target.camera}: "
        + ", ".join(f"{k} {v:.3f}" for k, v in mean.items() if v is not None)
    )
    print(f"wrote {out / 'attention.mp4'} and {out / 'attention.json'}")
    return out
