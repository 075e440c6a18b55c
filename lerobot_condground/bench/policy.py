"""Training-step and inference cost of the act_modified variants against stock ACT.

All policies see the same batch of a dataset recorded by the bench, on the same device, timed in
alternating rounds (each round starting with another policy); ratios are taken round by round
against stock ACT, then the median is reported.
A training step is what lerobot-train does per batch: preprocessor (copy-paste augmentation
included), forward, backward, optimizer step. Inference is the preprocessor plus one action-chunk
prediction at batch size 1, the latency a robot waits for whenever the action queue runs dry.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

import torch

from lerobot_condground.core.configs import check_at_least
from lerobot_condground.evaluation.checkpoints import resolve_device
from lerobot_condground.policies.act_modified.configuration_act_modified import VARIANTS

POLICIES = ("act", *VARIANTS)


@dataclass
class PolicyBenchConfig:
    # Measure the policies at all (needs a few minutes on a CPU at full model size).
    enable: bool = True
    # cpu, cuda, ...; auto (default): the best one here.
    device: str = "auto"
    batch_size: int = 8
    # Timed training steps and inferences per policy and round.
    steps: int = 3
    # Model width (ACT's default is 512); smaller for quick checks.
    dim_model: int = 512
    chunk_size: int = 100

    def __post_init__(self):
        check_at_least(self, "policy.", batch_size=1, steps=1, dim_model=8, chunk_size=1)


def _policy_config(name: str, cfg: PolicyBenchConfig, device: str, dataset_features: dict):
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.utils.constants import OBS_IMAGES, OBS_STATE
    from lerobot.utils.feature_utils import dataset_to_policy_features

    from lerobot_condground.policies.act_modified.configuration_act_modified import ACTModifiedConfig

    common = dict(
        device=device,
        pretrained_backbone_weights=None,
        push_to_hub=False,
        dim_model=cfg.dim_model,
        dim_feedforward=cfg.dim_model * 25 // 4,
        chunk_size=cfg.chunk_size,
        n_action_steps=cfg.chunk_size,
    )
    if name != "act":
        return ACTModifiedConfig(variant=name, **common)
    # Stock ACT gets the inputs act_modified keeps (state and cameras): it cannot take the label strings.
    inputs = {
        key: feature
        for key, feature in dataset_to_policy_features(dataset_features).items()
        if key == OBS_STATE or key.startswith(f"{OBS_IMAGES}.")
    }
    return ACTConfig(input_features=inputs, **common)


def _timed(fn, steps: int, device: str) -> float:
    start = time.perf_counter()
    for _ in range(steps):
        fn()
    if device == "cuda":
        torch.cuda.synchronize()
    return (time.perf_counter() - start) / steps


def bench_policies(repo_id: str, root: str, cfg: PolicyBenchConfig, rounds: int) -> dict:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    device = resolve_device(cfg.device)
    meta = LeRobotDataset(repo_id, root=root).meta
    dataset = LeRobotDataset(
        repo_id, root=root, delta_timestamps={"action": [i / meta.fps for i in range(cfg.chunk_size)]}
    )
    loader = torch.utils.data.DataLoader(
        dataset, batch_size=cfg.batch_size, shuffle=True, generator=torch.Generator().manual_seed(0)
    )
    batch = next(iter(loader))
    observation = {k: v[:1] for k, v in batch.items() if k.startswith("observation.")}

    measures = {}
    for name in POLICIES:
        torch.manual_seed(0)
        policy_cfg = _policy_config(name, cfg, device, meta.features)
        policy = make_policy(policy_cfg, ds_meta=meta)
        preprocessor, _ = make_pre_post_processors(policy_cfg, dataset_stats=meta.stats)
        optimizer = torch.optim.AdamW(policy.get_optim_params(), lr=1e-5)

        def train_step(policy=policy, preprocessor=preprocessor, optimizer=optimizer):
            policy.train()
            loss, _ = policy.forward(preprocessor(dict(batch)))
            loss.backward()
            optimizer.step()
            optimizer.zero_grad()

        def infer(policy=policy, preprocessor=preprocessor):
            policy.eval()
            with torch.no_grad():
                policy.predict_action_chunk(preprocessor(dict(observation)))

        train_step()  # warm-up: allocations, kernel selection, the augmentation's sprite bank
        infer()
        measures[name] = (train_step, infer)

    train = {name: [] for name in POLICIES}
    inference = {name: [] for name in POLICIES}
    for round_ in range(rounds):
        # Each round starts with another policy, so no policy always runs first (or after the same one).
        for name in POLICIES[round_ % len(POLICIES) :] + POLICIES[: round_ % len(POLICIES)]:
            train_step, infer = measures[name]
            train[name].append(_timed(train_step, cfg.steps, device))
            inference[name].append(_timed(infer, cfg.steps, device))

    results = {"policy_device": device, "policy_batch_size": cfg.batch_size}
    for name in POLICIES:
        results[f"{name}_train_step_s"] = statistics.median(train[name])
        results[f"{name}_train_samples_per_s"] = cfg.batch_size / results[f"{name}_train_step_s"]
        results[f"{name}_inference_s"] = statistics.median(inference[name])
        if name != "act":
            results[f"{name}_train_step_ratio"] = statistics.median(
                v / a for v, a in zip(train[name], train["act"])
            )
            results[f"{name}_inference_ratio"] = statistics.median(
                v / a for v, a in zip(inference[name], inference["act"])
            )
    results["act_modified_train_step_ratio"] = results["full_train_step_ratio"]
    results["act_modified_inference_ratio"] = results["full_inference_ratio"]
    return results
