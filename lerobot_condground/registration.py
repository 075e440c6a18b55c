"""Everything the plugin registers with LeRobot and gymnasium, imported by the entry module `lerobot_policy_condground`.

LeRobot's stock scripts import the plugin through the `lerobot_policy_condground` distribution name,
so these registrations are what makes `--env.type=condground` and `--policy.type=act_modified`
resolve with no extra flag, and what lets a saved preprocessor find the copy-paste step again.
"""

from lerobot_condground import (
    envs,  # noqa: F401  gym ids gym_condground/<task>
    policies,  # noqa: F401  PreTrainedConfig type "act_modified"
)
from lerobot_condground.cameras import config_ur3e_twin  # noqa: F401  CameraConfig type "ur3e_twin"
from lerobot_condground.envs import configs  # noqa: F401  EnvConfig type "condground"
from lerobot_condground.processors import (  # noqa: F401  condground_* ProcessorSteps
    copy_paste,
    decode_labels,
    instruction,
    rgb_cue,
)
from lerobot_condground.robots import config_ur3e  # noqa: F401  RobotConfig type "ur3e"
from lerobot_condground.teleoperators import (
    config_ur3e_teleops,  # noqa: F401  ur3e_freedrive/_keyboard/_expert
)
