"""`condground bench`: simulation, recording, policy and sweep throughput on this machine.

Each figure is measured in the same process, one after the other, on the same scene, so the ratios
(env step rate over render-only fps) compare like with like.
"""

from __future__ import annotations

import json
import shutil
import statistics
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np

from lerobot_condground.bench.policy import PolicyBenchConfig
from lerobot_condground.bench.sweep import SweepBenchConfig
from lerobot_condground.bench.training import TrainBenchConfig
from lerobot_condground.core.configs import check_at_least


@dataclass
class BenchConfig:
    task: str = "PickPlaceRandomBin-v0"
    condition: str = "full_mixed"
    observation_height: int = 240
    observation_width: int = 320
    # Seconds spent on each timed measurement, split over `rounds` alternating rounds.
    seconds: float = 3.0
    rounds: int = 5
    # Expert episodes recorded for the recording throughput.
    record_episodes: int = 3
    # Training-step and inference cost of act_modified against stock ACT, on the recorded episodes.
    policy: PolicyBenchConfig = field(default_factory=PolicyBenchConfig)
    # Sweep rollouts per minute and the speed-up with parallel workers.
    sweep: SweepBenchConfig = field(default_factory=SweepBenchConfig)
    # Training samples/s at the CPU training configuration, on its own small Task 1 dataset.
    train: TrainBenchConfig = field(default_factory=TrainBenchConfig)
    # Print one JSON object instead of a table.
    json: bool = False

    def __post_init__(self):
        check_at_least(self, "", seconds=0.1, rounds=1, record_episodes=1)


def _rate(fn, seconds: float) -> float:
    count, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        count += fn()
    return count / (time.perf_counter() - start)


def _env_stepper(env, policy):
    """A callable that advances `env` one step with `policy`, resetting with a new seed when done."""
    state = {"obs": env.reset(seed=0)[0], "seed": 0}
    if hasattr(policy, "reset"):
        policy.reset(env)

    def step() -> int:
        obs, _, terminated, truncated, _ = env.step(policy(state["obs"]))
        state["obs"] = obs
        if terminated or truncated or getattr(policy, "done", False):
            state["seed"] += 1
            state["obs"] = env.reset(seed=state["seed"])[0]
            if hasattr(policy, "reset"):
                policy.reset(env)
        return 1

    return step


def _interleaved_rates(measures: dict, seconds: float, rounds: int) -> dict[str, list[float]]:
    """Rates of every measure, taken in alternating rounds so that load changes on the machine hit
    all of them alike; ratios are then taken round by round."""
    for fn in measures.values():
        fn()  # warm-up: first render, first layout
    rates: dict[str, list[float]] = {name: [] for name in measures}
    for _ in range(rounds):
        for name, fn in measures.items():
            rates[name].append(_rate(fn, seconds / rounds))
    return rates


def run_bench(cfg: BenchConfig) -> dict:
    import mujoco

    from lerobot_condground.datasets.record import RecordConfig, RecordDatasetConfig, record
    from lerobot_condground.envs.configs import CondGroundEnvConfig
    from lerobot_condground.envs.expert import ScriptedExpert
    from lerobot_condground.envs.pickplace_env import PickPlaceEnv

    size = dict(observation_height=cfg.observation_height, observation_width=cfg.observation_width)
    env = PickPlaceEnv(task=cfg.task, condition=cfg.condition, **size)
    env.reset(seed=0)
    # Physics runs on its own copy of the settled scene, untouched by the stepping measures below.
    model, data = env.model, mujoco.MjData(env.model)
    mujoco.mj_copyData(data, model, env.data)

    def physics() -> int:
        mujoco.mj_step(model, data, nstep=100)
        return 100

    def render() -> int:
        env._render_rgb("top")
        return 1

    rng = np.random.default_rng(0)
    random_policy = lambda obs: rng.uniform(env.action_space.low, env.action_space.high).astype(np.float32)  # noqa: E731

    class Expert(ScriptedExpert):
        def __call__(self, obs):
            return self.act(obs)

    seg_env = PickPlaceEnv(task=cfg.task, condition=cfg.condition, segmentation=True, **size)
    expert_env = PickPlaceEnv(task=cfg.task, condition=cfg.condition, **size)
    # The servo interpolation's cost: 25 set points a step in Python against one mj_step call.
    direct_env = PickPlaceEnv(task=cfg.task, condition=cfg.condition, servo="direct", **size)
    rates = _interleaved_rates(
        {
            "physics_steps_per_s": physics,
            "render_fps": render,
            "env_steps_per_s": _env_stepper(env, random_policy),
            "env_steps_per_s_expert": _env_stepper(expert_env, Expert()),
            "env_steps_per_s_expert_servo_direct": _env_stepper(direct_env, Expert()),
            "env_steps_per_s_with_segmentation": _env_stepper(seg_env, Expert()),
        },
        cfg.seconds,
        cfg.rounds,
    )
    for e in (env, expert_env, direct_env, seg_env):
        e.close()
    results = {
        "task": cfg.task,
        "condition": cfg.condition,
        "resolution": [cfg.observation_height, cfg.observation_width],
        "physics_substeps_per_env_step": env.n_substeps,
        **{name: statistics.median(values) for name, values in rates.items()},
        "env_over_render_ratio": statistics.median(
            e / r for e, r in zip(rates["env_steps_per_s"], rates["render_fps"])
        ),
        "servo_interpolated_over_direct_ratio": statistics.median(
            i / d
            for i, d in zip(rates["env_steps_per_s_expert"], rates["env_steps_per_s_expert_servo_direct"])
        ),
    }

    tmp = tempfile.mkdtemp(prefix="condground_bench_")
    try:
        start = time.perf_counter()
        out = record(
            RecordConfig(
                env=CondGroundEnvConfig(task=cfg.task, condition=cfg.condition, **size),
                dataset=RecordDatasetConfig(
                    repo_id="local/bench", root=f"{tmp}/ds", num_episodes=cfg.record_episodes
                ),
                progress=False,
            )
        )
        elapsed = time.perf_counter() - start
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        frames = LeRobotDataset("local/bench", root=f"{tmp}/ds").meta.total_frames
        results["record_frames_per_s"] = frames / elapsed
        results["record_s_per_episode"] = elapsed / out["total_episodes"]
        if cfg.policy.enable:
            from lerobot_condground.bench.policy import bench_policies

            results |= bench_policies("local/bench", f"{tmp}/ds", cfg.policy, cfg.rounds)
        if cfg.sweep.enable:
            from pathlib import Path

            from lerobot_condground.bench.sweep import bench_sweep, save_bench_checkpoint

            checkpoint = save_bench_checkpoint(
                "local/bench", f"{tmp}/ds", Path(tmp) / "checkpoint", cfg.sweep
            )
            results |= bench_sweep(checkpoint, cfg.task, cfg.condition, cfg.sweep, tmp)
        if cfg.train.enable:
            from lerobot_condground.bench.training import bench_training
            from lerobot_condground.core.training import CPU_FRAME_SIZE

            height, width = CPU_FRAME_SIZE
            record(
                RecordConfig(
                    env=CondGroundEnvConfig(
                        task="PickPlaceFixedBin-v0", observation_height=height, observation_width=width
                    ),
                    dataset=RecordDatasetConfig(
                        repo_id="local/bench_train", root=f"{tmp}/train_ds", num_episodes=cfg.train.episodes
                    ),
                    progress=False,
                )
            )
            results |= bench_training("local/bench_train", f"{tmp}/train_ds", cfg.train, cfg.rounds)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    if cfg.json:
        print(json.dumps(results))
    else:
        rows = dict(_flat(results))
        width = max(len(k) for k in rows)
        for key, value in rows.items():
            print(f"{key:<{width}}  {value:.2f}" if isinstance(value, float) else f"{key:<{width}}  {value}")
    return results


def _flat(results: dict, prefix: str = ""):
    for key, value in results.items():
        if isinstance(value, dict):
            yield from _flat(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value
