"""The scripted expert (the `ur3e_expert` teleoperator) through the `ur3e` robot on its MuJoCo twin, with
the robot's default safety limits: how many scenes end with the object placed.

    .venv/bin/python examples/ur3e_twin_expert.py --scenes=5 --condition=full_mixed --realtime=true
"""

import argparse
import time

from lerobot_condground.robots.config_ur3e import UR3eConfig, UR3eSimConfig
from lerobot_condground.robots.ur3e import UR3e
from lerobot_condground.teleoperators.config_ur3e_teleops import UR3eExpertConfig
from lerobot_condground.teleoperators.ur3e_teleops import UR3eExpert


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scenes", type=int, default=5)
    parser.add_argument("--condition", default="full_mixed")
    parser.add_argument("--realtime", default="true", choices=("true", "false"))
    args = parser.parse_args()
    realtime = args.realtime == "true"
    robot = UR3e(UR3eConfig(backend="sim", sim=UR3eSimConfig(condition=args.condition, realtime=realtime)))
    teleop = UR3eExpert(UR3eExpertConfig())
    teleop.connect()
    placed = 0
    with robot:
        period = 1 / robot.config.control_hz
        for scene in range(args.scenes):
            if scene:
                robot.new_episode()
            start = time.perf_counter()
            for steps in range(1, 401):  # noqa: B007  (read after the loop)
                t0 = time.perf_counter()
                robot.get_observation()
                robot.send_action(teleop.get_action())
                if teleop.expert.done:
                    break
                if realtime:
                    time.sleep(max(0.0, period - (time.perf_counter() - t0)))
            placed += robot.arm.env.tracker.place
            print(
                f"scene {scene}: placed={robot.arm.env.tracker.place} steps={steps} "
                f"({time.perf_counter() - start:.1f} s) watchdog stops={robot.arm.state().stalls}",
                flush=True,
            )
    teleop.disconnect()
    print(f"placed {placed}/{args.scenes} ({args.condition}, {'real time' if realtime else 'lock-step'})")


if __name__ == "__main__":
    main()
