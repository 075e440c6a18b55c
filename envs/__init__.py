"""Simulated pick-and-place with look-alike distractors, and the instrument-routing task (gym ids
`gym_condground/<task>`).

Registration uses string entry points so that importing the plugin never imports MuJoCo.
"""

import gymnasium as gym

from lerobot_condground.core.conditions import ROUTING_TASK, TASKS

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
_id = f"{GYM_NAMESPACE}/{ROUTING_TASK}"
if _id not in gym.registry:
    gym.register(
        id=_id, entry_point="lerobot_condground.envs.routing_env:InstrumentRoutingEnv", max_episode_steps=300
    )
