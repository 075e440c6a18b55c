"""Cost of `pi05_grounded`'s regularizer and of gradient checkpointing at π0.5's full size (a GPU job).

One model (random weights, the configured dtype) is built once; per batch size, the four settings
(regularizer off/on x checkpointing off/on) are timed in alternating rounds, each round starting with
another setting, and the ratios to `plain` (both off) are taken round by round, median reported. A training
step is forward, backward and an AdamW step on a synthetic InstrumentRouting-like batch (two cameras, the
route step's masks); peak memory is the device's allocator peak during that setting's steps (CUDA only).
`select_action` latency is one action chunk at batch 1. A setting that runs out of memory is reported as
such, not as a failure of the run.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field

import torch

from lerobot_condground.core.configs import check_at_least
from lerobot_condground.core.routing import DESTINATION, OTHER_CONTAINER, STEPS
from lerobot_condground.evaluation.checkpoints import resolve_device

CAMERAS = ("observation.images.top", "observation.images.wrist")
SETTINGS = {  # name -> (regularizer, gradient checkpointing)
    "plain": (False, False),
    "regularized": (True, False),
    "checkpointed": (False, True),
    "regularized_checkpointed": (True, True),
}


@dataclass
class Pi05BenchConfig:
    device: str = "auto"
    dtype: str = "bfloat16"
    batch_sizes: list[int] = field(default_factory=lambda: [8, 32])
    steps: int = 3  # timed training steps per setting and round
    rounds: int = 2
    image_size: int = 224  # frames as the env renders them (square: π0.5's input size needs no padding)
    image_resolution: int = 224  # π0.5's input size
    chunk_size: int = 50
    tokens: int = 200  # tokenizer_max_length

    def __post_init__(self):
        check_at_least(self, "", steps=1, rounds=1, image_size=8, image_resolution=8, chunk_size=1, tokens=8)
        if not self.batch_sizes or min(self.batch_sizes) < 1:
            raise ValueError(f"--batch_sizes={self.batch_sizes} is not allowed; allowed: sizes >= 1")


def _policy(cfg: Pi05BenchConfig, device: str):
    from lerobot.configs.types import FeatureType, PolicyFeature

    from lerobot_condground.policies.pi05_grounded.configuration_pi05_grounded import PI05GroundedConfig
    from lerobot_condground.policies.pi05_grounded.modeling_pi05_grounded import PI05GroundedPolicy

    config = PI05GroundedConfig(
        device=device, dtype=cfg.dtype, chunk_size=cfg.chunk_size, n_action_steps=cfg.chunk_size,
        image_resolution=(cfg.image_resolution, cfg.image_resolution), tokenizer_max_length=cfg.tokens,
        instruction="generic", push_to_hub=False,
    )  # fmt: skip
    shape = (3, cfg.image_size, cfg.image_size)
    config.input_features = {c: PolicyFeature(FeatureType.VISUAL, shape) for c in CAMERAS}
    config.input_features["observation.state"] = PolicyFeature(FeatureType.STATE, (7,))
    config.input_features |= {
        k: PolicyFeature(FeatureType.STATE, (1,))
        for k in ("observation.segmentation", "observation.segmentation_wrist", "observation.phase")
    }
    config.output_features = {"action": PolicyFeature(FeatureType.ACTION, (7,))}
    return PI05GroundedPolicy(config)


def _batch(cfg: Pi05BenchConfig, policy, batch_size: int, device: str) -> dict:
    g = torch.Generator().manual_seed(0)
    n, s = batch_size, cfg.image_size
    vocab = policy.model.paligemma_with_expert.paligemma.config.text_config.vocab_size
    seg = torch.zeros(n, s, s, dtype=torch.uint8)
    seg[:, : s // 4, : s // 4] = DESTINATION
    seg[:, -s // 4 :, -s // 4 :] = OTHER_CONTAINER
    batch = {
        **{c: torch.rand(n, 3, s, s, generator=g) for c in CAMERAS},
        "observation.state": torch.rand(n, 7, generator=g) * 2 - 1,
        "observation.language.tokens": torch.randint(0, vocab, (n, cfg.tokens), generator=g),
        "observation.language.attention_mask": torch.ones(n, cfg.tokens, dtype=torch.bool),
        "action": torch.rand(n, cfg.chunk_size, 7, generator=g) * 2 - 1,
        "observation.segmentation": seg,
        "observation.segmentation_wrist": seg.clone(),
        "observation.phase": torch.full((n, 1), STEPS.index("route")),
    }
    return {k: v.to(device) for k, v in batch.items()}


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def bench_pi05(cfg: Pi05BenchConfig) -> dict:
    device = resolve_device(cfg.device)
    cuda = device.startswith("cuda")
    start = time.perf_counter()
    torch.manual_seed(0)
    policy = _policy(cfg, device)
    results: dict = {
        "device": device,
        "dtype": cfg.dtype,
        "parameters": sum(p.numel() for p in policy.parameters()),
        "build_s": time.perf_counter() - start,
    }
    optimizer = torch.optim.AdamW([p for p in policy.parameters() if p.requires_grad], lr=1e-5)

    def step(batch: dict, regularized: bool, checkpointed: bool) -> None:
        policy.config.use_grounding_loss = regularized
        toggle = (
            policy.model.gradient_checkpointing_enable
            if checkpointed
            else policy.model.gradient_checkpointing_disable
        )
        toggle()
        policy.train()
        loss, _ = policy.forward(batch)
        loss.backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)

    for batch_size in cfg.batch_sizes:
        batch = _batch(cfg, policy, batch_size, device)
        times: dict[str, list[float]] = {name: [] for name in SETTINGS}
        peaks: dict[str, float] = {}
        failed: set[str] = set()
        names = list(SETTINGS)
        for round_ in range(cfg.rounds + 1):  # round 0 warms up each setting and measures its memory
            for name in names[round_ % len(names) :] + names[: round_ % len(names)]:
                if name in failed:
                    continue
                if cuda and round_ == 0:
                    torch.cuda.reset_peak_memory_stats()
                try:
                    _sync(device)
                    t0 = time.perf_counter()
                    for _ in range(cfg.steps if round_ else 1):
                        step(batch, *SETTINGS[name])
                    _sync(device)
                except torch.OutOfMemoryError:
                    failed.add(name)
                    optimizer.zero_grad(set_to_none=True)
                    torch.cuda.empty_cache()
                    continue
                if round_ == 0:
                    peaks[name] = torch.cuda.max_memory_allocated() / 2**30 if cuda else float("nan")
                else:
                    times[name].append((time.perf_counter() - t0) / cfg.steps)
        for name in SETTINGS:
            key = f"b{batch_size}_{name}"
            if name in failed:
                results[f"{key}_step_s"] = "out of memory"
                continue
            results[f"{key}_step_s"] = statistics.median(times[name])
            results[f"{key}_peak_gib"] = peaks[name]
            if name != "plain" and "plain" not in failed:
                results[f"{key}_step_ratio"] = statistics.median(
                    t / p for t, p in zip(times[name], times["plain"])
                )
        del batch

    policy.eval()
    observation = {k: v for k, v in _batch(cfg, policy, 1, device).items() if k != "action"}
    latencies = []
    for _ in range(cfg.rounds + 1):
        policy.reset()
        _sync(device)
        t0 = time.perf_counter()
        with torch.no_grad():
            policy.select_action(observation)
        _sync(device)
        latencies.append(time.perf_counter() - t0)
    results["select_action_s"] = statistics.median(latencies[1:])
    return results
