"""lerobot-condground: conditional visual grounding for LeRobot policies.

Importing this package registers everything the plugin provides with LeRobot and gymnasium. It stays
cheap: MuJoCo and hardware SDKs are imported only when an environment or device is created.
"""

import os

# Headless rendering unless the user chose a backend; MuJoCo reads this when it is first imported.
os.environ.setdefault("MUJOCO_GL", "egl")

from . import registration  # noqa: E402,F401

__version__ = "0.1.0"
