"""Simulated pick-and-place with look-alike distractors (gym ids `gym_condground/<task>`).

Registration uses string entry points so that importing the plugin never imports MuJoCo.
"""

import gymnasium as gym

from lerobot_condground.core.conditions import TASKS

GYM_NAMESPACE = "gym_condground"

for _task in TASKS:
    _id = f"{GYM_NAMESPACE}/{_task}"
    if _id not in gym.registry:
        gym.register(
            id=_id,
            entry_point="lerobot_condground.envs.pickplace_env:PickPlaceEnv",
            kwargs={"task": _task},
            max_episode_steps=300,
        )
