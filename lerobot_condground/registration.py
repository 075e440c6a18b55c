"""Everything the plugin registers with LeRobot and gymnasium, imported once by the package.

LeRobot's stock scripts import the plugin through the `lerobot_policy_condground` distribution name,
so these registrations are what makes `--env.type=condground` resolve with no extra flag.
"""

from lerobot_condground import envs  # noqa: F401  gym ids gym_condground/<task>
from lerobot_condground.envs import configs  # noqa: F401  EnvConfig type "condground"
