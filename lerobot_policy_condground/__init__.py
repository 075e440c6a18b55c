import lerobot_condground  # noqa: F401  (LeRobot discovers plugins by distribution name and imports this module)
