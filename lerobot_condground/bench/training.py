"""Training throughput at the CPU training configuration (`core.training`), as lerobot-train spends it.

One step is what lerobot-train does per batch: the next batch from a DataLoader over the LeRobotDataset
(video decoding, label strings, the action chunk's rows), the preprocessor (label decoding, copy-paste),
forward, backward, gradient clipping, AdamW. Every policy trains on its own loader over the same dataset
(recorded by the bench at the configuration's frame size) in alternating rounds; medians are reported.

- each act_modified variant at the configuration, with decoded frames held in memory (`condground train`);
- stock ACT with the same settings (its own backbone: torchvision's ResNet-18 with frozen batch norm);
- `full` without the frame cache (`lerobot-train`): the cache's own speed-up, same model;
- `full` on today's path: LeRobot's defaults for what the configuration changes (full-width ResNet-18
  with frozen batch norm, the CVAE), no frame cache;
- `standard` under bf16 autocast, where the configuration turns it on (`core.training.amp_flags`: AMX).
"""

from __future__ import annotations

import contextlib
import dataclasses
import statistics
import time
from dataclasses import dataclass

import torch

from lerobot_condground.core.configs import check_at_least
from lerobot_condground.core.training import CPU_BATCH_SIZE, CPU_POLICY, amp_flags
from lerobot_condground.datasets.frame_cache import FrameCache
from lerobot_condground.policies.act_modified.configuration_act_modified import VARIANTS

PLAIN = {"backbone_width": 64, "backbone_norm": "frozen_batchnorm", "use_vae": True}


@dataclass
class TrainBenchConfig:
    enable: bool = True
    # torch threads of the training process (the configuration trains one run per core).
    threads: int = 1
    batch_size: int = CPU_BATCH_SIZE
    # Timed training steps per policy and round.
    steps: int = 3
    # Expert episodes recorded for the bench (Task 1, clean, at the configuration's frame size).
    episodes: int = 2
    # Model width override for quick checks (None: the configuration's).
    dim_model: int | None = None

    def __post_init__(self):
        check_at_least(self, "train.", threads=1, batch_size=1, steps=1, episodes=1, dim_model=8)


def _configs(cfg: TrainBenchConfig, features: dict) -> dict:
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.utils.constants import OBS_IMAGES, OBS_STATE
    from lerobot.utils.feature_utils import dataset_to_policy_features

    from lerobot_condground.policies.act_modified.configuration_act_modified import ACTModifiedConfig

    policy = dict(CPU_POLICY, device="cpu", push_to_hub=False)
    if cfg.dim_model is not None:
        policy |= {"dim_model": cfg.dim_model, "dim_feedforward": 4 * cfg.dim_model}
    configs = {name: ACTModifiedConfig(variant=name, **policy) for name in VARIANTS}
    configs["full_uncached"] = ACTModifiedConfig(variant="full", **policy)
    configs["full_plain"] = ACTModifiedConfig(variant="full", **(policy | PLAIN))
    if amp_flags():
        configs["standard_bf16"] = ACTModifiedConfig(variant="standard", use_amp=True, **policy)
    # Stock ACT takes the configuration's fields it has (not the narrow backbone, its norm or the schedule).
    stock = {k: v for k, v in policy.items() if k in {f.name for f in dataclasses.fields(ACTConfig)}}
    inputs = {  # stock ACT takes state and cameras; the label strings stay in the batch, unread
        key: feature
        for key, feature in dataset_to_policy_features(features).items()
        if key == OBS_STATE or key.startswith(f"{OBS_IMAGES}.")
    }
    configs["act"] = ACTConfig(input_features=inputs, **stock)
    return configs


def _trainer(policy_cfg, meta, repo_id, root, batch_size, split: dict[str, float], cache: FrameCache | None):
    """A callable running one training step; adds its data / preprocess / update seconds to `split`.
    With `cache`, batches are read while the frame cache is active."""
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    torch.manual_seed(0)
    policy = make_policy(policy_cfg, ds_meta=meta)
    preprocessor, _ = make_pre_post_processors(policy_cfg, dataset_stats=meta.stats)
    optimizer_cfg = policy_cfg.get_optimizer_preset()
    optimizer, clip = optimizer_cfg.build(policy.get_optim_params()), optimizer_cfg.grad_clip_norm
    dataset = LeRobotDataset(repo_id, root=root, delta_timestamps=resolve_delta_timestamps(policy_cfg, meta))
    loader = torch.utils.data.DataLoader(
        dataset,
        batch_size=batch_size,
        shuffle=True,
        drop_last=True,
        generator=torch.Generator().manual_seed(0),
    )
    batches = iter(loader)
    policy.train()

    def step() -> None:
        nonlocal batches
        start = time.perf_counter()
        with cache or contextlib.nullcontext():
            batch = next(batches, None)
            if batch is None:
                batches = iter(loader)
                batch = next(batches)
        loaded = time.perf_counter()
        batch = preprocessor(batch)
        processed = time.perf_counter()
        # as lerobot-train's update step: forward under autocast, backward and AdamW outside it
        with torch.autocast("cpu", enabled=policy_cfg.use_amp):
            loss, _ = policy.forward(batch)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), clip)
        optimizer.step()
        optimizer.zero_grad()
        done = time.perf_counter()
        split["data"] += loaded - start
        split["preprocess"] += processed - loaded
        split["update"] += done - processed

    return step


def bench_training(repo_id: str, root: str, cfg: TrainBenchConfig, rounds: int) -> dict:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    threads = torch.get_num_threads()
    torch.set_num_threads(cfg.threads)
    try:
        dataset = LeRobotDataset(repo_id, root=root)
        meta = dataset.meta
        cache = FrameCache(max_gb=4)
        with cache:  # every frame decoded once, as after the first epoch of a run
            for index in range(len(dataset)):
                dataset[index]
        configs = _configs(cfg, meta.features)
        splits = {name: dict.fromkeys(("data", "preprocess", "update"), 0.0) for name in configs}
        steps = {
            name: _trainer(
                c,
                meta,
                repo_id,
                root,
                cfg.batch_size,
                splits[name],
                None if name.startswith("full_") else cache,
            )
            for name, c in configs.items()
        }
        for step in steps.values():
            step()  # warm-up: allocations, kernel selection, the decoder, the augmentation's sprite bank
        for split in splits.values():
            split.update(dict.fromkeys(split, 0.0))
        rates: dict[str, list[float]] = {name: [] for name in steps}
        names = list(steps)
        for round_ in range(rounds):
            for name in names[round_ % len(names) :] + names[: round_ % len(names)]:
                start = time.perf_counter()
                for _ in range(cfg.steps):
                    steps[name]()
                rates[name].append(cfg.steps * cfg.batch_size / (time.perf_counter() - start))
    finally:
        torch.set_num_threads(threads)

    median = {name: statistics.median(values) for name, values in rates.items()}
    bf16 = {}
    if "standard_bf16" in rates:
        bf16 = {
            "train_samples_per_s_standard_bf16": median["standard_bf16"],
            "train_bf16_speedup": statistics.median(
                b / f for b, f in zip(rates["standard_bf16"], rates["standard"], strict=True)
            ),
        }
    return bf16 | {
        "train_threads": cfg.threads,
        "train_batch_size": cfg.batch_size,
        "train_samples_per_s": {name: median[name] for name in VARIANTS},
        "train_samples_per_s_act": median["act"],
        "train_samples_per_s_full_plain": median["full_plain"],
        "train_samples_per_s_full_uncached": median["full_uncached"],
        "train_cache_speedup": statistics.median(
            f / u for f, u in zip(rates["full"], rates["full_uncached"], strict=True)
        ),
        "train_speedup_vs_plain": statistics.median(
            f / p for f, p in zip(rates["full"], rates["full_plain"], strict=True)
        ),
        # Seconds per step spent loading the batch, in the preprocessor, and in forward/backward/AdamW.
        "train_step_split_s": {
            name: {part: seconds / (rounds * cfg.steps) for part, seconds in split.items()}
            for name, split in splits.items()
        },
    }
