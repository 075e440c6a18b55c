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
- with `--train.options=true` (default), `bench.training_options`: the ceiling and each speed option.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import statistics
import time
from dataclasses import dataclass

import torch

from lerobot_condground.core.configs import check_at_least
from lerobot_condground.core.training import CPU_BATCH_SIZE, CPU_POLICY
from lerobot_condground.datasets.frame_cache import FrameCache
from lerobot_condground.policies.act_modified.configuration_act_modified import VARIANTS

PLAIN = {"backbone_width": 64, "backbone_norm": "frozen_batchnorm", "use_vae": True}
PHASES = ("data", "preprocess", "forward", "backward", "optimizer")


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
    # The ceiling and each speed option against the current path (bench.training_options).
    options: bool = True
    # torch.compile among the options (inductor compiles for minutes on one core).
    compile: bool = True
    # Batch sizes the kept path is timed at, separated by commas.
    batch_sizes: str = "32,64"
    # One run on two threads against two runs on one thread each (separate processes).
    thread_layouts: bool = True
    # Seconds spent measuring each peak (a matmul and a convolution, per precision).
    peak_seconds: float = 3.0

    def __post_init__(self):
        check_at_least(
            self, "train.", threads=1, batch_size=1, steps=1, episodes=1, dim_model=8, peak_seconds=0.1
        )
        try:
            self.batch_list()
        except ValueError:
            raise ValueError(
                f"--train.batch_sizes={self.batch_sizes} is not allowed; allowed: whole numbers >= 1 separated by "
                "commas (e.g. 32,64)"
            ) from None

    def batch_list(self) -> list[int]:
        sizes = [int(s) for s in self.batch_sizes.split(",") if s.strip()]
        if any(s < 1 for s in sizes):
            raise ValueError(self.batch_sizes)
        return sizes


def _configs(cfg: TrainBenchConfig, features: dict) -> dict:
    """name -> (policy config, how it trains)."""
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.utils.constants import OBS_IMAGES, OBS_STATE
    from lerobot.utils.feature_utils import dataset_to_policy_features

    configs = {name: (policy_config(name, dim_model=cfg.dim_model), Option()) for name in VARIANTS}
    configs["full_uncached"] = (configs["full"][0], Option(cache=False))
    configs["full_plain"] = (policy_config("full", dim_model=cfg.dim_model, **PLAIN), Option(cache=False))
    # Stock ACT takes the configuration's fields it has (not the narrow backbone, its norm or the schedule).
    own = {f.name for f in dataclasses.fields(ACTConfig)}
    stock = {k: getattr(configs["standard"][0], k) for k in CPU_POLICY if k in own}
    inputs = {  # stock ACT takes state and cameras; the label strings stay in the batch, unread
        key: feature
        for key, feature in dataset_to_policy_features(features).items()
        if key == OBS_STATE or key.startswith(f"{OBS_IMAGES}.")
    }
    configs["act"] = (ACTConfig(input_features=inputs, device="cpu", push_to_hub=False, **stock), Option())
    return configs


@dataclass(frozen=True)
class Option:
    """How a training step runs (not what it computes): `condground train`'s frame cache, channels-last
    memory order, bf16 autocast, oneDNN's bf16 arithmetic for fp32 layers, `torch.compile`."""

    cache: bool = True
    channels_last: bool = False
    amp: bool = False
    onednn_bf16: bool = False
    compile: bool = False


@contextlib.contextmanager
def onednn_bf16(enabled: bool):
    """oneDNN computing fp32 convolutions and matmuls in bf16 (weights and results stay fp32)."""
    backends = (torch.backends.mkldnn.conv, torch.backends.mkldnn.matmul)
    before = [b.fp32_precision for b in backends]
    if enabled:
        for b in backends:
            b.fp32_precision = "bf16"
    try:
        yield
    finally:
        for b, value in zip(backends, before, strict=True):
            b.fp32_precision = value


def policy_config(variant: str, option: Option = Option(), dim_model: int | None = None, **fields):
    """act_modified at the CPU configuration (with `fields` changed), trained as `option` says."""
    from lerobot_condground.policies.act_modified.configuration_act_modified import ACTModifiedConfig

    policy = dict(CPU_POLICY, device="cpu", push_to_hub=False) | fields
    if dim_model is not None:
        policy |= {"dim_model": dim_model, "dim_feedforward": 4 * dim_model}
    return ACTModifiedConfig(
        variant=variant, channels_last=option.channels_last, use_amp=option.amp, **policy
    )


class Trainer:
    """lerobot-train's step for one policy on its own shuffled DataLoader over the dataset, its seconds
    added up by phase (`PHASES`); with `cache` (a FrameCache) and `option.cache`, batches are read while
    the frame cache is active."""

    def __init__(self, policy_cfg, option: Option, repo_id: str, root: str, batch_size: int, cache=None):
        from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
        from lerobot.datasets.factory import resolve_delta_timestamps
        from lerobot.datasets.lerobot_dataset import LeRobotDataset
        from lerobot.policies.factory import make_policy, make_pre_post_processors

        torch.manual_seed(0)
        meta = LeRobotDatasetMetadata(repo_id, root=root)
        self.policy = make_policy(policy_cfg, ds_meta=meta)
        self.preprocessor, _ = make_pre_post_processors(policy_cfg, dataset_stats=meta.stats)
        optimizer_cfg = policy_cfg.get_optimizer_preset()
        self.optimizer = optimizer_cfg.build(self.policy.get_optim_params())
        self.clip = optimizer_cfg.grad_clip_norm
        dataset = LeRobotDataset(
            repo_id, root=root, delta_timestamps=resolve_delta_timestamps(policy_cfg, meta)
        )
        self.loader = torch.utils.data.DataLoader(
            dataset, batch_size=batch_size, shuffle=True, drop_last=True,
            generator=torch.Generator().manual_seed(0),
        )  # fmt: skip
        self.batches = iter(self.loader)
        self.option, self.cache, self.batch_size = option, cache if option.cache else None, batch_size
        self.policy.train()
        self.forward = torch.compile(self.policy.forward) if option.compile else self.policy.forward
        self.compile_s = 0.0
        self.reset()
        if option.compile:
            start = time.perf_counter()
            self.step()  # inductor compiles forward and backward here
            self.compile_s = time.perf_counter() - start
        self.reset()

    def reset(self) -> None:
        self.seconds = dict.fromkeys(PHASES, 0.0)
        self.steps = 0

    def next_batch(self) -> dict:
        with self.cache or contextlib.nullcontext():
            batch = next(self.batches, None)
            if batch is None:
                self.batches = iter(self.loader)
                batch = next(self.batches)
        return batch

    def step(self) -> None:
        from torch.profiler import record_function

        times = [time.perf_counter()]
        with record_function("data"):
            batch = self.next_batch()
        times.append(time.perf_counter())
        with record_function("preprocess"):
            batch = self.preprocessor(batch)
        times.append(time.perf_counter())
        with onednn_bf16(self.option.onednn_bf16):
            # as lerobot-train's update: forward under autocast, backward and AdamW outside it
            with record_function("forward"), torch.autocast("cpu", enabled=self.policy.config.use_amp):
                loss, _ = self.forward(batch)
            times.append(time.perf_counter())
            with record_function("backward"):
                loss.backward()
            times.append(time.perf_counter())
        with record_function("optimizer"):
            torch.nn.utils.clip_grad_norm_(self.policy.parameters(), self.clip)
            self.optimizer.step()
            self.optimizer.zero_grad()
        times.append(time.perf_counter())
        for phase, (start, end) in zip(PHASES, itertools.pairwise(times), strict=True):
            self.seconds[phase] += end - start
        self.steps += 1

    def samples_per_s(self, steps: int) -> float:
        start = time.perf_counter()
        for _ in range(steps):
            self.step()
        return steps * self.batch_size / (time.perf_counter() - start)


def alternating_rates(trainers: dict, steps: int, rounds: int) -> dict[str, list[float]]:
    """Samples/s of every trainer, `steps` steps a round, each round starting with the next trainer, so
    that load changes on the machine hit all alike; ratios are then taken round by round."""
    for trainer in trainers.values():
        trainer.step()  # warm-up: allocations, kernel selection, the decoder, the augmentation's sprite bank
        trainer.reset()
    rates: dict = {name: [] for name in trainers}
    names = list(trainers)
    for round_ in range(rounds):
        for name in names[round_ % len(names) :] + names[: round_ % len(names)]:
            rates[name].append(trainers[name].samples_per_s(steps))
    return rates


def filled_cache(dataset) -> FrameCache:
    """A frame cache holding every frame of the dataset, decoded once, as after the first epoch of a run."""
    cache = FrameCache(max_gb=4)
    with cache:
        for index in range(len(dataset)):
            dataset[index]
    return cache


def ratio(rates: dict, a, b) -> float:
    return statistics.median(x / y for x, y in zip(rates[a], rates[b], strict=True))


def bench_training(repo_id: str, root: str, cfg: TrainBenchConfig, rounds: int) -> dict:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_condground.bench.training_options import bench_options

    threads = torch.get_num_threads()
    torch.set_num_threads(cfg.threads)
    try:
        dataset = LeRobotDataset(repo_id, root=root)
        cache = filled_cache(dataset)
        trainers = {
            name: Trainer(policy_cfg, option, repo_id, root, cfg.batch_size, cache)
            for name, (policy_cfg, option) in _configs(cfg, dataset.meta.features).items()
        }
        rates = alternating_rates(trainers, cfg.steps, rounds)
        median = {name: statistics.median(values) for name, values in rates.items()}
        result = {
            "train_threads": cfg.threads,
            "train_batch_size": cfg.batch_size,
            "train_samples_per_s": {name: median[name] for name in VARIANTS},
            "train_samples_per_s_act": median["act"],
            "train_samples_per_s_full_plain": median["full_plain"],
            "train_samples_per_s_full_uncached": median["full_uncached"],
            "train_cache_speedup": ratio(rates, "full", "full_uncached"),
            "train_speedup_vs_plain": ratio(rates, "full", "full_plain"),
            # Seconds per step spent loading the batch, in the preprocessor, and in forward/backward/AdamW.
            "train_step_split_s": {
                name: {
                    "data": t.seconds["data"] / t.steps,
                    "preprocess": t.seconds["preprocess"] / t.steps,
                    "update": sum(t.seconds[p] for p in ("forward", "backward", "optimizer")) / t.steps,
                }
                for name, t in trainers.items()
            },
        }
        del trainers  # a model and its optimizer state each: the options build their own
        if cfg.options:
            result |= bench_options(repo_id, root, cfg, rounds, cache)
    finally:
        torch.set_num_threads(threads)
    return result
