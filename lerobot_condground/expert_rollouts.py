"""Runs the scripted expert closed-loop, without rendering: the oracle check of the environment."""

from __future__ import annotations

from tqdm import tqdm


def expert_stages(
    task: str, condition: str, episodes: int, counterbalanced: bool = False, seed: int = 0, progress: bool = True
) -> list[int]:
    """Stage index reached in each of `episodes` expert episodes (seeds seed .. seed+episodes-1)."""
    from lerobot_condground.envs.expert import ScriptedExpert
    from lerobot_condground.envs.pickplace_env import PickPlaceEnv
    from lerobot_condground.record import run_expert_episode

    env = PickPlaceEnv(task=task, condition=condition, counterbalanced=counterbalanced, obs_type="agent_pos")
    expert = ScriptedExpert()
    stages = []
    for k in tqdm(range(episodes), desc=f"expert {task} {condition}", unit="ep", disable=not progress, leave=False):
        info = run_expert_episode(env, expert, seed + k, max_steps=300)
        stages.append(int(info["stage"]))
    env.close()
    return stages
