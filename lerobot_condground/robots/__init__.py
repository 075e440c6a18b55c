"""The `ur3e` LeRobot robot: one class over two arm backends, ur_rtde (hardware) and the MuJoCo twin.

Only the config is imported at plugin discovery; LeRobot imports `robots.ur3e` (the robot class) when a
`--robot.type=ur3e` robot is made, and ur_rtde is imported only inside the arm's own process.
"""
