"""The hardware path of the `ur3e` robot against a loopback fake UR controller (RTDE, dashboard, Robotiq
URCap socket, script ports) running as its own process: real ur_rtde clients, our worker process, real
sockets. The receive path runs with `--robot.dry_run=true` (read everything, command nothing); the control
path (servoJ, servoStop, teachMode) runs against the fake's emulation of ur_rtde's control script."""

import json
import os
import pty
import signal
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest

from helpers import BIN
from lerobot_condground.envs.robot import MOTOR_NAMES
from lerobot_condground.robots.config_ur3e import UR3eConfig
from lerobot_condground.robots.grippers import DigitalOutputGripper, RobotiqSocketGripper
from lerobot_condground.robots.safety import ArmFault
from lerobot_condground.robots.ur3e import UR3e
from lerobot_condground.teleoperators.config_ur3e_teleops import UR3eExpertConfig
from lerobot_condground.teleoperators.ur3e_teleops import UR3eExpert
from ur_fake import free_loopback_host, start_fake_controller

Q = [0.1, -1.6, 1.5, -1.4, -1.57, 0.3]


def robot_for(host, **kwargs) -> UR3e:
    return UR3e(UR3eConfig(host=host, dry_run=True, connect_timeout_s=8.0, **kwargs))


@pytest.fixture
def fake():
    with start_fake_controller(free_loopback_host(), actual_q=Q) as controller:
        yield controller


def test_receive_path_reads_joints_gripper_and_keeps_other_threads_running(fake):
    fake.set(gripper={"position": 120})
    robot = robot_for(fake.host, joint_offsets=[0.5, 0, 0, 0, 0, 0])
    ticks = []
    beat = threading.Event()

    def heartbeat():  # stands in for LeRobot's camera threads: ur_rtde must not freeze this process
        while not beat.is_set():
            ticks.append(time.perf_counter())
            time.sleep(0.01)

    thread = threading.Thread(target=heartbeat)
    thread.start()
    try:
        robot.connect()
        obs = robot.get_observation()
    finally:
        beat.set()
        thread.join()
    try:
        np.testing.assert_allclose(
            [obs[k] for k in MOTOR_NAMES[:6]], np.add(Q, [0.5, 0, 0, 0, 0, 0]), atol=1e-9
        )
        assert obs["gripper.pos"] == pytest.approx(120 / 255, abs=0.01)
        fake.set(actual_q=[0.0] * 6)
        time.sleep(0.05)
        assert robot.get_observation()["shoulder_pan.pos"] == pytest.approx(0.5)
        assert max(np.diff(ticks)) < 0.2  # the heartbeat never stalled while the arm connected
        assert fake.state()["gripper"]["ACT"] == 0  # dry run: the gripper was read, not activated
        # ur_rtde raises the thread that builds an RTDE interface: that happens in the worker process alone,
        # so this process, and what it launches, stay at normal priority (issue 56).
        if hasattr(os, "sched_getscheduler"):
            assert os.sched_getscheduler(0) == os.SCHED_OTHER
            child = [sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"]
            assert subprocess.run(child, check=True, capture_output=True, text=True).stdout.strip() == "0"
    finally:
        robot.disconnect()
    assert not robot.is_connected


def test_protective_stop_surfaces_as_an_error_and_is_never_resumed(fake):
    robot = robot_for(fake.host)
    robot.connect()
    worker = robot.arm.process
    robot.get_observation()
    fake.set(safety_mode=3)
    deadline = time.perf_counter() + 1.0
    with pytest.raises(ArmFault, match="protective stop"):
        while time.perf_counter() < deadline:
            robot.get_observation()
            time.sleep(0.005)
    fake.set(safety_mode=1)  # cleared on the pendant: the robot still refuses until reconnected
    with pytest.raises(ArmFault):
        robot.send_action(dict.fromkeys(MOTOR_NAMES, 0.0))
    worker.join(timeout=3)
    assert not worker.is_alive()
    robot.disconnect()


@pytest.mark.parametrize(
    "state, words",
    [
        ({"robot_model": "UR5"}, "reports robot model 'UR5'"),
        ({"safety_mode": 7}, "robot emergency stop"),
    ],
)
def test_connect_refuses_the_wrong_arm_or_a_stopped_one(state, words):
    with start_fake_controller(free_loopback_host(), **state) as fake:
        robot = robot_for(fake.host)
        with pytest.raises(ConnectionError, match=words):
            robot.connect()
        assert not robot.is_connected and robot.arm is None


def test_local_control_mode_is_refused_before_the_control_script_is_started():
    with start_fake_controller(free_loopback_host(), is_in_remote_control=False) as fake:
        robot = UR3e(UR3eConfig(host=fake.host, connect_timeout_s=8.0))
        with pytest.raises(ConnectionError, match="Local Control"):
            robot.connect()
        assert fake.state()["scripts"] == []


def test_unreachable_host_fails_fast():
    robot = robot_for(free_loopback_host())  # nothing listens there
    start = time.perf_counter()
    with pytest.raises(ConnectionError, match="unreachable"):
        robot.connect()
    assert time.perf_counter() - start < 2


def test_a_controller_that_never_answers_times_out(fake):
    fake.mode(dashboard="silent")
    robot = UR3e(UR3eConfig(host=fake.host, dry_run=True, connect_timeout_s=1.5))
    start = time.perf_counter()
    with pytest.raises(ConnectionError) as err:
        robot.connect()
    # Which of the two fires first depends on ur_rtde's own timers; both name the host, the port and the checks.
    assert f"{fake.host}:29999" in str(err.value) and "accepted the connection but did not" in str(err.value)
    assert "Check that the controller has finished booting" in str(err.value)
    assert time.perf_counter() - start < 5 and robot.arm is None


def test_worker_releases_the_arm_when_the_parent_dies(fake):
    script = textwrap.dedent(f"""
        import time
        from lerobot_condground.robots.config_ur3e import UR3eConfig
        from lerobot_condground.robots.ur3e import UR3e
        robot = UR3e(UR3eConfig(host={fake.host!r}, dry_run=True, gripper="none"))
        robot.connect()
        print("connected", robot.arm.process.pid, flush=True)
        time.sleep(60)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith("connected"), line
        worker = int(line.split()[1])
        assert len(fake.state()["rtde_sessions"]) == 1
        proc.send_signal(signal.SIGKILL)  # the policy process dies without a word
        proc.wait()
        assert fake.wait_for(lambda s: len(s["rtde_sessions"]) == 0, timeout=5)
        with pytest.raises(ProcessLookupError):
            for _ in range(50):
                os.kill(worker, 0)
                time.sleep(0.1)
    finally:
        proc.kill()


def test_robotiq_socket_gripper_activates_moves_and_reads(fake):
    gripper = RobotiqSocketGripper(fake.host)
    gripper.connect()
    assert fake.state()["gripper"]["STA"] == 3
    gripper.command(1.0)
    deadline = time.perf_counter() + 3
    while gripper.closure() < 0.85 and time.perf_counter() < deadline:
        time.sleep(0.05)
    assert gripper.closure() > 0.85  # the fingers travelled to (near) closed
    gripper.command(0.0)
    time.sleep(0.2)
    assert gripper.closure() < 0.85
    gripper.close()


def test_tool_digital_output_gripper_through_rtde_io(fake):
    # ur_rtde holds the GIL while it blocks: the client runs in a subprocess, as in the worker.
    script = textwrap.dedent(f"""
        import time, rtde_receive
        from lerobot_condground.robots.grippers import DigitalOutputGripper
        g = DigitalOutputGripper({fake.host!r}, output=1)
        g.connect()
        g.command(0.9)
        time.sleep(0.1)
        r = rtde_receive.RTDEReceiveInterface({fake.host!r})
        print("closure", g.closure_from_bits(r.getActualDigitalOutputBits()), flush=True)
        import os; os._exit(0)
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=30)
    assert "closure 1.0" in out.stdout, out.stderr[-2000:]
    assert fake.state()["tool_digital_outputs"] == [False, True]
    with pytest.raises(ValueError, match="outputs 0 and 1"):
        DigitalOutputGripper(fake.host, output=2)


# ---------------------------------------------------------------------- control path (emulated script)
CONTROL_SERVERS = ("rtde", "dashboard", "gripper", "script")


@pytest.fixture
def controller():
    with start_fake_controller(free_loopback_host(), servers=CONTROL_SERVERS, actual_q=Q) as fake:
        yield fake


def action(q, gripper=0.0) -> dict:
    return dict(zip(MOTOR_NAMES, [*map(float, q), float(gripper)], strict=True))


@pytest.mark.realtime
def test_servoj_stream_interpolates_within_limits_and_a_stall_stops_it(controller):
    """Through the real RTDEControlInterface: 500 Hz servoJ set points between 20 Hz targets, the speed
    limit on every set point, the configured lookahead/gain, and servoStop two control periods after the
    stream of targets stopped."""
    robot = UR3e(UR3eConfig(host=controller.host, connect_timeout_s=10.0, servoj_gain=500))
    robot.connect()
    try:
        controller.clear_logs()
        q = np.array(Q)
        for _ in range(20):  # base joint at 1 rad/s for 1 s
            q[0] += 0.05
            robot.send_action(action(q, gripper=1.0))
            time.sleep(0.05)
        assert controller.wait_for(lambda s: any(e["cmd"] == "servo_stop" for e in s["servo_log"]), timeout=2)
        state = controller.state()
        log = state["servo_log"]
        servo = [e for e in log if e["cmd"] == "servoj"]
        stop = next(e for e in log if e["cmd"] == "servo_stop")
        t = np.array([e["t"] for e in servo])
        setpoints = np.array([e["q"] for e in servo])
        assert 350 < 1 / np.median(np.diff(t)) < 600  # the servo rate
        assert np.abs(np.diff(setpoints, axis=0)).max() <= 2.0 * 0.002 * 1.05  # velocity limit per tick
        assert state["servo_lookahead"] == pytest.approx(0.1) and state["servo_gain"] == pytest.approx(500)
        assert setpoints[-1][0] == pytest.approx(q[0], abs=1e-6)  # the last target was reached
        reached = t[np.argmax(np.abs(setpoints[:, 0] - q[0]) < 1e-9)]
        # Stopped at most two periods after the last command, which the set points reach one period after it.
        assert stop["t"] - reached <= 0.05 + 0.03
        # The arm followed (behind its set point by servoJ's lookahead, then braked by servoStop).
        assert robot.get_observation()["shoulder_pan.pos"] > Q[0] + 0.8
        assert state["gripper"]["PRE"] > 200  # the Robotiq was told to close
    finally:
        robot.disconnect()
    cmds = [e["cmd"] for e in controller.state()["servo_log"]]
    assert "stop_script" in cmds[-3:] and not controller.state()["control_script_running"]


def test_protective_stop_while_streaming(controller):
    robot = UR3e(UR3eConfig(host=controller.host, gripper="none"))
    robot.connect()
    try:
        q = np.array(Q)
        for _ in range(4):
            q[1] += 0.02
            robot.send_action(action(q))
            time.sleep(0.05)
        controller.set(safety_mode=3)
        with pytest.raises(ArmFault, match="protective stop|control script stopped"):
            for _ in range(40):
                q[1] += 0.01
                robot.send_action(action(q))
                time.sleep(0.05)
    finally:
        robot.disconnect()


FREEDRIVE_SCRIPT = """
import sys, time
from lerobot_condground.robots.config_ur3e import UR3eConfig
from lerobot_condground.robots.ur3e import UR3e
from lerobot_condground.teleoperators.config_ur3e_teleops import UR3eFreedriveConfig
from lerobot_condground.teleoperators.ur3e_teleops import UR3eFreedrive
teleop = UR3eFreedrive(UR3eFreedriveConfig())
teleop.connect()
robot = UR3e(UR3eConfig(host=sys.argv[1], gripper="none"))
robot.connect()
for i in range(40):
    robot.get_observation()
    action = teleop.get_action()
    robot.send_action(action)
    if i == 0:
        print("teaching", flush=True)
    time.sleep(0.05)
print("last", action["shoulder_pan.pos"], action["gripper.pos"], flush=True)
robot.disconnect()
teleop.disconnect()
"""


def test_freedrive_teleop_records_the_hand_guided_joints(controller):
    """Teach mode through the real control interface; the joints a hand puts the arm in are the actions, and
    a key (typed into a pseudo-terminal) toggles the gripper."""
    master, slave = pty.openpty()
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.Popen(
        [sys.executable, "-c", FREEDRIVE_SCRIPT, controller.host],
        stdin=slave,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    os.close(slave)
    try:
        lines = iter(proc.stdout.readline, "")
        assert any(line.strip() == "teaching" for line in lines)
        assert controller.wait_for(lambda s: s["teach_mode"], timeout=3)
        controller.set(actual_q=[0.7, *Q[1:]])  # the hand moves the base joint
        os.write(master, b" ")
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
        os.close(master)
    last = out.split()
    assert last[0] == "last", out + err[-2000:]
    assert float(last[1]) == pytest.approx(0.7) and float(last[2]) == 1.0
    cmds = [e["cmd"] for e in controller.state()["servo_log"]]
    assert "teach_mode" in cmds and "end_teach_mode" in cmds and "stop_script" in cmds[-3:]
    assert not any(c == "servoj" for c in cmds[cmds.index("teach_mode") : cmds.index("end_teach_mode")])


def test_lerobot_calibrate_stores_the_home_pose(controller, tmp_path):
    proc = subprocess.run(
        [
            str(BIN / "lerobot-calibrate"),
            "--robot.type=ur3e",
            f"--robot.host={controller.host}",
            "--robot.id=lab",
            f"--robot.calibration_dir={tmp_path}",
            "--robot.gripper=none",
        ],
        input="\n",
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, f"rc {proc.returncode}\n{proc.stdout[-1500:]}\n{proc.stderr[-1500:]}"
    assert json.loads((tmp_path / "lab.json").read_text())["home"] == pytest.approx(Q)
    # The calibrated arm, found elsewhere, goes home on connect through the safety layer.
    controller.set(actual_q=[Q[0] + 0.3, *Q[1:]])
    robot = UR3e(
        UR3eConfig(
            host=controller.host,
            id="lab",
            calibration_dir=tmp_path,
            gripper="none",
            move_home_on_connect=True,
        )
    )
    assert robot.home == pytest.approx(Q)
    start = time.perf_counter()
    robot.connect()
    try:
        assert time.perf_counter() - start > 0.3 / 0.5 * 0.9  # at the homing speed, not in one jump
        assert controller.state()["servo_target"] == pytest.approx(Q, abs=1e-6)
    finally:
        robot.disconnect()


def test_expert_teleop_refuses_the_real_arm(fake):
    teleop = UR3eExpert(UR3eExpertConfig())
    teleop.connect()
    with robot_for(fake.host, gripper="none") as robot:
        for _ in range(2):
            with pytest.raises(ValueError, match="use it with --robot.backend=sim"):
                teleop.get_action()
        assert robot.is_connected
