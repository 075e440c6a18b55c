"""The plugin's entry module: LeRobot's `register_third_party_plugins()` imports installed distributions named
`lerobot_policy_*`, and this import registers everything lerobot-condground provides with LeRobot and gymnasium."""

from lerobot_condground import registration  # noqa: F401
