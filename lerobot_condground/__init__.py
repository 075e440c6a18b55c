"""lerobot-condground: conditional visual grounding for LeRobot policies.

Importing this package registers everything the plugin provides with LeRobot and gymnasium. It stays
cheap: MuJoCo and hardware SDKs are imported only when an environment or device is created.
"""

import os

# Headless rendering unless the user chose a backend; MuJoCo reads this when it is first imported.
os.environ.setdefault("MUJOCO_GL", "egl")

import multiprocessing  # noqa: E402

# The UR3e's arm worker (robots.rtde_arm) is a spawned process that needs none of the registrations, and
# importing them (torch, LeRobot's policies) would add seconds to every robot connect.
if not multiprocessing.current_process().name.startswith("ur3e-arm-worker"):
    from . import registration  # noqa: F401

__version__ = "0.1.0"
