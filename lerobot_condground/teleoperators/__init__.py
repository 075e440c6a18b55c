"""LeRobot teleoperator types for the UR3e: `ur3e_freedrive`, `ur3e_keyboard`, `ur3e_expert`."""
