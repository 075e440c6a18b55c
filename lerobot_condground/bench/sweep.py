"""The sweep part of `condground bench`: rollouts per minute for one cell, and the speed-up with workers.

The policy is an act_modified `full` at ACT's default size built on the bench's recorded episodes
(random weights: it runs every episode to the step limit, the most expensive case). Every worker
count runs the same cell (same layouts) through `run_sweep`, pool start-up and policy loading
included, with one thread per worker so that the speed-up measures scaling over cores.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from lerobot_condground.core.configs import check_at_least, usable_cores


@dataclass
class SweepBenchConfig:
    enable: bool = True
    # Worker counts to compare, e.g. "1,2,4" (default: 1 and all cores).
    workers: str = ""
    episodes: int = 48
    batch_size: int = 4
    episode_length: int = 100
    device: str = "cpu"
    dim_model: int = 512

    def __post_init__(self):
        check_at_least(self, "sweep.", episodes=1, batch_size=1, episode_length=1, dim_model=8)


def save_bench_checkpoint(repo_id: str, root: str, out: Path, cfg: SweepBenchConfig) -> Path:
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    from lerobot_condground.policies.act_modified.configuration_act_modified import ACTModifiedConfig

    torch.manual_seed(0)
    meta = LeRobotDataset(repo_id, root=root).meta
    policy_cfg = ACTModifiedConfig(
        variant="full",
        device=cfg.device,
        pretrained_backbone_weights=None,
        push_to_hub=False,
        dim_model=cfg.dim_model,
        dim_feedforward=cfg.dim_model * 25 // 4,
    )
    policy = make_policy(policy_cfg, ds_meta=meta)
    preprocessor, postprocessor = make_pre_post_processors(policy_cfg, dataset_stats=meta.stats)
    for part in (policy, preprocessor, postprocessor):
        part.save_pretrained(out)
    return out


def bench_sweep(checkpoint: Path, task: str, condition: str, cfg: SweepBenchConfig, tmp: str) -> dict:
    from lerobot_condground.core.configs import EvalEnvConfig, PolicyRefConfig
    from lerobot_condground.evaluation.results import read_table
    from lerobot_condground.evaluation.sweep import SweepConfig, SweepEvalConfig, SweepGridConfig, run_sweep

    cores = usable_cores()
    counts = [int(w) for w in cfg.workers.split(",")] if cfg.workers else sorted({1, cores})
    results: dict = {
        "sweep_episodes": cfg.episodes,
        "sweep_episode_length": cfg.episode_length,
        "sweep_cores": cores,
    }
    rates = {}
    for workers in counts:
        sweep = SweepConfig(
            policy=PolicyRefConfig(paths=str(checkpoint), device=cfg.device),
            env=EvalEnvConfig(task=task, episode_length=cfg.episode_length),
            sweep=SweepGridConfig(conditions=condition),
            eval=SweepEvalConfig(seeds=1, n_episodes=cfg.episodes, batch_size=cfg.batch_size),
            output_dir=f"{tmp}/sweep_{workers}",
            workers=workers,
            threads_per_worker=1,
            progress=False,
        )
        start = time.perf_counter()
        rows = read_table(run_sweep(sweep))
        elapsed = time.perf_counter() - start
        rates[workers] = len(rows) / elapsed * 60
        results[f"sweep_rollouts_per_min_{workers}_workers"] = rates[workers]
        results[f"sweep_env_steps_per_s_{workers}_workers"] = rows.steps.sum() / elapsed
    for workers in counts:
        if workers > 1 and 1 in rates:
            results[f"sweep_speedup_{workers}_workers"] = rates[workers] / rates[1]
            results[f"sweep_speedup_per_worker_{workers}_workers"] = rates[workers] / rates[1] / workers
    return results
