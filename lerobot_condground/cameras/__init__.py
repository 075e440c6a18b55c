"""LeRobot camera types of the plugin: `ur3e_twin`, the cameras of the UR3e's MuJoCo twin."""
