"""The hardware path of the `ur3e` robot against a loopback fake UR controller (RTDE, dashboard, Robotiq
URCap socket) running as its own process: real ur_rtde clients, our worker process, real sockets.

The control script (servoJ, teachMode) cannot run without a controller, so these tests use
`--robot.dry_run=true` (read everything, command nothing) for the receive path; the control path runs
through the same ServoLoop and safety layer, tested on the twin (test_ur3e_twin)."""

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest
from ur_fake import free_loopback_host, start_fake_controller

from lerobot_condground.envs.robot import MOTOR_NAMES
from lerobot_condground.robots.config_ur3e import UR3eConfig
from lerobot_condground.robots.grippers import DigitalOutputGripper, RobotiqSocketGripper
from lerobot_condground.robots.safety import ArmFault
from lerobot_condground.robots.ur3e import UR3e

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
        np.testing.assert_allclose([obs[k] for k in MOTOR_NAMES[:6]], np.add(Q, [0.5, 0, 0, 0, 0, 0]), atol=1e-9)
        assert obs["gripper.pos"] == pytest.approx(120 / 255, abs=0.01)
        fake.set(actual_q=[0.0] * 6)
        time.sleep(0.05)
        assert robot.get_observation()["shoulder_pan.pos"] == pytest.approx(0.5)
        assert max(np.diff(ticks)) < 0.2  # the heartbeat never stalled while the arm connected
        assert fake.state()["gripper"]["ACT"] == 0  # dry run: the gripper was read, not activated
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


@pytest.mark.parametrize("state, words", [
    ({"robot_model": "UR5"}, "reports robot model 'UR5'"),
    ({"safety_mode": 7}, "robot emergency stop"),
])
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
    with pytest.raises(ConnectionError, match="did not finish connecting within 1.5 s|Operation canceled"):
        robot.connect()
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
