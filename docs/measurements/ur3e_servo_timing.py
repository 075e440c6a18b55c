"""Servo-stream timing of the ur3e's arm worker against the loopback fake controller (tests/ur_fake).

The worker streams servoJ through the real ur_rtde RTDEControlInterface; the fake timestamps every set
point it receives. Prints the achieved servo rate against the configured one (as a ratio) and the
interval distribution, for 2 s of 20 Hz targets:

    .venv/bin/python docs/measurements/ur3e_servo_timing.py
"""

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))

from lerobot_condground.core.ur3e import MOTOR_NAMES  # noqa: E402
from lerobot_condground.robots.config_ur3e import UR3eConfig  # noqa: E402
from lerobot_condground.robots.ur3e import UR3e  # noqa: E402
from ur_fake import free_loopback_host, start_fake_controller  # noqa: E402

Q = [0.1, -1.6, 1.5, -1.4, -1.57, 0.3]


def main() -> None:
    servers = ("rtde", "dashboard", "gripper", "script")
    with start_fake_controller(free_loopback_host(), servers=servers, actual_q=Q) as fake:
        config = UR3eConfig(host=fake.host, gripper="none")
        robot = UR3e(config)
        t0 = time.perf_counter()
        robot.connect()
        connect_s = time.perf_counter() - t0
        fake.clear_logs()
        q = np.array(Q)
        for _ in range(int(2 * config.control_hz)):
            t0 = time.perf_counter()
            q[0] += 0.04
            robot.send_action(dict(zip(MOTOR_NAMES, [*q, 0.0], strict=True)))
            time.sleep(max(0.0, 1 / config.control_hz - (time.perf_counter() - t0)))
        robot.disconnect()
        t = np.array([e["t"] for e in fake.state()["servo_log"] if e["cmd"] == "servoj"])
    dt = np.diff(t) * 1e3
    rate = (len(t) - 1) / (t[-1] - t[0])
    print(f"connect: {connect_s:.2f} s")
    print(
        f"servoJ set points: {len(t)}, rate {rate:.1f} Hz of {config.servo_hz:.0f} Hz (ratio {rate / config.servo_hz:.3f})"
    )
    print(
        f"interval ms: mean {dt.mean():.2f}, p50 {np.median(dt):.2f}, p99 {np.percentile(dt, 99):.2f}, max {dt.max():.2f}"
    )


if __name__ == "__main__":
    main()
