"""`condground prompts-bench`: per-frame tracking latency of the prompt segmenters (color, SAM 2) here,
on the frames of one simulated expert episode, with the privileged clicks on its two targets."""

from __future__ import annotations

import json
import logging
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lerobot_condground.labelling.prompts import click_on


@dataclass
class PromptsBenchConfig:
    # Frame size the trackers run at (the simulation's default camera).
    height: int = 240
    width: int = 320
    # Tracked frames per segmenter (after one annotated frame and `warmup` untimed ones; SAM 2's untimed
    # frames are at least its memory bank's 7, whose filling makes each next frame slower).
    frames: int = 20
    warmup: int = 2
    # Also time the random-weight model of sam2.1-hiera-tiny's architecture (1024x1024; seconds per
    # frame on a CPU), with this many frames (0: skip it).
    tiny_frames: int = 3
    # A real SAM 2 checkpoint to time as well (hub id in the local cache, or a directory); none by default.
    model_id: str | None = None
    device: str = "cpu"
    dtype: str = "float32"
    json: bool = False


def _sim_frames(height: int, width: int, n: int, seed: int = 5):
    """Frames of one expert episode (clean scene) and the privileged clicks on its two targets."""
    from lerobot_condground.envs.expert import ScriptedExpert
    from lerobot_condground.envs.pickplace_env import PickPlaceEnv

    env = PickPlaceEnv(
        task="PickPlaceRandomBin-v0",
        condition="clean",
        observation_height=height,
        observation_width=width,
        segmentation=True,
    )
    obs, _ = env.reset(seed=seed)
    expert = ScriptedExpert()
    expert.reset(env)
    frames, first_seg = [], obs["segmentation"]
    while len(frames) < n:
        frames.append(obs["pixels"]["top"])
        obs, _, terminated, truncated, _ = env.step(expert.act(obs))
        if terminated or truncated:
            obs, _ = env.reset(seed=seed)
            expert.reset(env)
    env.close()
    return frames, [click_on(first_seg, label) for label in (1, 2)]


def time_tracking(segmenter, frames, object_prompt, receptacle_prompt, warmup: int = 2) -> dict:
    """ms per tracked frame of a PromptTracker over `frames`, and ms for the annotated first frame (what the
    robot's live prompt cameras pay once per episode)."""
    from lerobot_condground.labelling.prompt_tracker import PromptTracker

    tracker = PromptTracker(segmenter)
    t0 = time.perf_counter()
    tracker.start(frames[0], object_prompt, receptacle_prompt)
    start_ms = 1000 * (time.perf_counter() - t0)
    times = []
    for i, frame in enumerate(frames[1:]):
        t0 = time.perf_counter()
        tracker.track(frame)
        if i >= warmup:
            times.append(1000 * (time.perf_counter() - t0))
    return {
        "frames": len(times),
        "mean_ms": float(np.mean(times)),
        "p95_ms": float(np.percentile(times, 95)),
        "warmup": warmup,
        "start_ms": start_ms,
    }


def bench_prompts(cfg: PromptsBenchConfig) -> dict:
    """Per-frame tracking latency of both segmenters on this machine at cfg.height x cfg.width."""
    import torch

    from lerobot_condground.labelling.segmenters import ColorSegmenter, Sam2Segmenter, save_random_sam2

    sam2_warmup = max(cfg.warmup, 7)  # Sam2VideoConfig.num_maskmem: the memory bank is full from then on
    n = max(cfg.frames, cfg.tiny_frames) + sam2_warmup + 1
    frames, (obj, rec) = _sim_frames(cfg.height, cfg.width, n)
    rows = {}
    rows["color"] = time_tracking(
        ColorSegmenter(), frames[: cfg.frames + cfg.warmup + 1], obj, rec, cfg.warmup
    )
    # Random weights segment nothing: the tracker's empty-mask warnings are expected and not shown.
    tracker_log = logging.getLogger("lerobot_condground.labelling.prompt_tracker")
    level = tracker_log.level
    tracker_log.setLevel(logging.ERROR)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            models = [("sam2 small random (2.3M params, 256x256 input)", "small", cfg.frames)]
            if cfg.tiny_frames > 0:
                models.append(
                    (
                        "sam2.1-hiera-tiny architecture, random (38.96M params, 1024x1024 input)",
                        "tiny",
                        cfg.tiny_frames,
                    )
                )
            for name, size, count in models:
                path = save_random_sam2(Path(tmp) / size, size=size)
                seg = Sam2Segmenter(model_id=str(path), device=cfg.device, dtype=cfg.dtype)
                rows[name] = time_tracking(seg, frames[: count + sam2_warmup + 1], obj, rec, sam2_warmup)
                del seg
    finally:
        tracker_log.setLevel(level)
    if cfg.model_id:
        seg = Sam2Segmenter(model_id=cfg.model_id, device=cfg.device, dtype=cfg.dtype)
        rows[f"sam2 {cfg.model_id}"] = time_tracking(
            seg, frames[: cfg.frames + sam2_warmup + 1], obj, rec, sam2_warmup
        )
    return {
        "height": cfg.height,
        "width": cfg.width,
        "device": cfg.device,
        "dtype": cfg.dtype,
        "torch_threads": torch.get_num_threads(),
        "segmenters": rows,
    }


def format_bench(result: dict) -> str:
    lines = [
        f"per-frame tracking latency at {result['width']}x{result['height']} on {result['device']} "
        f"({result['dtype']}, {result['torch_threads']} torch threads), object + receptacle:"
    ]
    for name, row in result["segmenters"].items():
        lines.append(
            f"  {name:<75} mean {row['mean_ms']:9.1f} ms  p95 {row['p95_ms']:9.1f} ms  "
            f"({row['frames']} frames after {row['warmup']}); first frame {row['start_ms']:8.1f} ms"
        )
    return "\n".join(lines)


def run_bench(cfg: PromptsBenchConfig) -> dict:
    result = bench_prompts(cfg)
    print(json.dumps(result, indent=1) if cfg.json else format_bench(result))
    return result
