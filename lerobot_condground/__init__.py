"""lerobot-condground: conditional visual grounding for LeRobot policies.

Importing this package is cheap and registers nothing: LeRobot's scripts register the plugin through its
entry module `lerobot_policy_condground` (see `registration.py`), our `condground` command does the same,
and a process that needs neither (the UR3e's arm worker) pays for neither.
"""

import os

# Headless rendering unless the user chose a backend; MuJoCo reads this when it is first imported.
os.environ.setdefault("MUJOCO_GL", "egl")

__version__ = "0.1.0"
