"""Units of evaluation work: one checkpoint, condition and evaluation seed, a batch of paired episodes.

A unit becomes a job (a plain dict a spawned or Ray worker can take), and its finished rows are one
part file whose name says which unit it holds. The sweep and the prompt-swap probe both cut their
work this way and run it on the launchers of `launchers.py`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from lerobot_condground.core.configs import EvalEnvConfig
from lerobot_condground.evaluation.checkpoints import LoadedPolicy
from lerobot_condground.evaluation.results import read_table
from lerobot_condground.evaluation.rollout import EnvSpec

PARTS = "parts"
EPISODES_PER_SEED_LIMIT = 100_000


@dataclass(frozen=True)
class Unit:
    checkpoint: int  # index into the run's checkpoints
    condition: str
    eval_seed: int
    start: int
    stop: int

    def part_path(self, root: Path, checkpoint_hash: str) -> Path:
        safe = re.sub(r"[^A-Za-z0-9_]+", "-", self.condition)
        return (
            root
            / PARTS
            / checkpoint_hash
            / safe
            / f"seed{self.eval_seed:03d}_ep{self.start:05d}-{self.stop:05d}.parquet"
        )


def layout_seed(seed_offset: int, eval_seed: int, episode: int) -> int:
    """Paired by construction: episode e of evaluation seed s has the same layout whatever the condition
    or checkpoint."""
    return seed_offset + eval_seed * EPISODES_PER_SEED_LIMIT + episode


def check_part(path: Path, unit: Unit, checkpoint_hash: str):
    """A finished part must hold exactly its unit's episodes; anything else is a clear error."""
    frame = read_table(path)
    expected = list(range(unit.start, unit.stop))
    problems = []
    if sorted(frame["episode"].tolist()) != expected:
        problems.append(
            f"episodes {sorted(frame['episode'].tolist())} instead of {unit.start}..{unit.stop - 1}"
        )
    for column, value in (
        ("checkpoint_hash", checkpoint_hash),
        ("condition", unit.condition),
        ("eval_seed", unit.eval_seed),
    ):
        if set(frame[column].tolist()) != {value}:
            problems.append(f"{column} {sorted(set(frame[column].tolist()))} instead of {value!r}")
    if problems:
        raise ValueError(
            f"Partial results file {path} does not match its unit ({'; '.join(problems)}); delete it to rerun those episodes"
        )
    return frame


def make_jobs(
    env: EvalEnvConfig, seed_offset: int, device: str, units: list[Unit], checkpoints: list[LoadedPolicy]
) -> list[dict]:
    jobs = []
    for unit in units:
        loaded = checkpoints[unit.checkpoint]
        episodes = list(range(unit.start, unit.stop))
        jobs.append(
            {
                "unit": unit,
                "checkpoint": loaded,  # as described and checked: its private copy loads
                "device": device,
                "env": EnvSpec.for_checkpoint(env, loaded, unit.condition),
                "episodes": episodes,
                "seeds": [layout_seed(seed_offset, unit.eval_seed, e) for e in episodes],
                "identity": {
                    **loaded.identity(),
                    "task": env.task,
                    "condition": unit.condition,
                    "counterbalanced": env.counterbalanced,
                    "eval_seed": unit.eval_seed,
                    "prompt": "target",
                },
            }
        )
    return jobs


_POLICIES: dict = {}
_POOL = None


def run_unit(job: dict) -> list[dict]:
    """Runs one job in this process; policies and envs are cached across the jobs a worker gets."""
    import torch

    from lerobot_condground.evaluation.checkpoints import load_policy
    from lerobot_condground.evaluation.rollout import EnvPool, run_episodes

    global _POOL
    _POOL = _POOL or EnvPool()
    spec: EnvSpec = job["env"]
    key = (job["checkpoint"].local, job["device"], spec.observation_height, spec.observation_width)
    if key not in _POLICIES:
        _POLICIES[key] = load_policy(job["checkpoint"], spec.lerobot_config(), job["device"])
    loaded = _POLICIES[key]
    envs = _POOL.get(spec, len(job["seeds"]))
    torch.manual_seed(job["seeds"][0])
    outcomes = run_episodes(loaded, envs, job["seeds"], max_steps=spec.episode_length, swap=job.get("swap"))
    return [
        {**job["identity"], "episode": episode, "layout_seed": seed, **result}
        for episode, seed, result in zip(job["episodes"], job["seeds"], outcomes)
    ]
