"""The fake UR e-Series controller (tests/ur_fake) against the REAL ur_rtde 1.6.5 clients.

ur_rtde's native calls hold the GIL and some block for seconds on a bad peer, so every client runs in a
subprocess with a timeout; the client scripts print one JSON line that the test then checks. The fake
itself is another subprocess, reached over its JSON side channel.
"""

import json
import socket
import struct
import subprocess
import sys
import textwrap
import time

import pytest

from ur_fake import FakeControllerError, forward_kinematics, free_loopback_host, start_fake_controller

# Shared by the client scripts: one side-channel request from inside the client process, so a state
# change and the client's view of it are timed on one clock.
CLIENT_PRELUDE = textwrap.dedent("""
    import json, os, socket, sys, time
    def done(result):
        # Skips ur_rtde's destructors (each receive interface spends ~0.5 s joining its thread).
        print(json.dumps(result), flush=True)
        os._exit(0)
    def side(host, line):
        with socket.create_connection((host, 30099), timeout=5) as s:
            s.sendall(line.encode() + b"\\n")
            buf = b""
            while not buf.endswith(b"\\n"):
                buf += s.recv(1 << 20)
        return json.loads(buf)
    def until(fn, timeout=1.0):
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            if fn():
                return time.monotonic() - t0
            time.sleep(0.0005)
        return None
""")


def run_client(code: str, timeout: float = 15.0) -> dict:
    """Runs client code in a fresh interpreter; returns the JSON it prints last."""
    proc = subprocess.run(
        [sys.executable, "-c", CLIENT_PRELUDE + textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln[:1] in ("{", "[")]
    assert proc.returncode == 0 and lines, f"client failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    return json.loads(lines[-1])


@pytest.fixture(scope="module")
def fake():
    with start_fake_controller(free_loopback_host(), gripper={"activation_s": 0.05}) as f:
        yield f


def test_receive_interface_reads_state_and_follows_side_channel(fake):
    q = [0.1, -1.2, 1.3, -1.6, -1.5, 0.2]
    fake.set(actual_q=q, safety_mode=1, robot_mode=7)
    out = run_client(f"""
        import rtde_receive
        host = {fake.host!r}
        r = rtde_receive.RTDEReceiveInterface(host)
        first = dict(q=r.getActualQ(), mode=r.getRobotMode(), safety=r.getSafetyMode(), ts=r.getTimestamp(),
                     tcp=r.getActualTCPPose(), runtime=r.getRuntimeState(), status=r.getRobotStatus(),
                     pstop=r.isProtectiveStopped(), connected=r.isConnected())
        time.sleep(0.1)
        ts2 = r.getTimestamp()
        new_q = [0.0, -1.0, 1.0, -1.0, -1.0, 0.5]
        side(host, "set " + json.dumps({{"safety_mode": 3, "actual_q": new_q}}))
        lat = until(lambda: r.getSafetyMode() == 3 and r.getActualQ() == new_q)
        pstop = r.isProtectiveStopped()
        side(host, "set " + json.dumps({{"safety_mode": 7}}))
        lat_e = until(lambda: r.isEmergencyStopped())
        side(host, "set " + json.dumps({{"safety_mode": 1}}))
        r.disconnect()
        print(json.dumps(dict(first=first, ts2=ts2, lat=lat, pstop=pstop, lat_e=lat_e)))
    """)
    first = out["first"]
    assert first["connected"] and first["q"] == q
    assert first["mode"] == 7 and first["safety"] == 1 and not first["pstop"]
    assert first["runtime"] == 1 and first["status"] == 1  # program stopped; bit 0: power on
    assert first["tcp"] == pytest.approx(forward_kinematics(q, "UR3"), abs=1e-9)
    assert 0.05 < out["ts2"] - first["ts"] < 0.5  # controller time advances with wall time
    assert abs(out["ts2"] / 0.002 - round(out["ts2"] / 0.002)) < 1e-6  # 2 ms control cycles
    assert out["lat"] is not None and out["lat"] < 0.05, out
    assert out["pstop"] is True
    assert out["lat_e"] is not None and out["lat_e"] < 0.05

    st = fake.state()
    setup = [e for e in st["events"] if e["event"] == "output_setup"][-1]
    assert setup["ok"] and setup["frequency"] == 500.0  # e-Series rate chosen from the 'v' reply
    assert "NOT_FOUND" not in setup["types"] and {"actual_q", "safety_status_bits", "ft_raw_wrench"} <= set(
        setup["names"]
    )


def test_io_interface_sets_tool_outputs_seen_by_receive(fake):
    fake.set(actual_digital_output_bits=0)
    out = run_client(f"""
        import rtde_receive, rtde_io
        host = {fake.host!r}
        r = rtde_receive.RTDEReceiveInterface(host)
        io = rtde_io.RTDEIOInterface(host)
        ok = io.setToolDigitalOut(0, True)
        lat = until(lambda: r.getActualDigitalOutputBits() == 1 << 16)
        io.setToolDigitalOut(1, True); io.setToolDigitalOut(0, False)
        lat2 = until(lambda: r.getActualDigitalOutputBits() == 1 << 17)
        io.setStandardDigitalOut(2, True); io.setSpeedSlider(0.25)
        until(lambda: r.getDigitalOutState(2) and r.getTargetSpeedFraction() == 0.25)
        after = dict(bits=r.getActualDigitalOutputBits(), slider=r.getTargetSpeedFraction())
        try:  # a second client may not take inputs the first holds: the controller answers IN_USE
            rtde_io.RTDEIOInterface(host)
            second = "connected"
        except RuntimeError as exc:
            second = str(exc)
        done(dict(ok=ok, lat=lat, lat2=lat2, after=after, second=second))
    """)
    assert out["ok"] is True and out["lat"] is not None and out["lat2"] is not None
    assert out["after"] == {"bits": (1 << 17) | (1 << 2), "slider": 0.25}
    assert "already in use" in out["second"]
    st = fake.state()
    assert st["tool_digital_outputs"] == [False, True]
    tool_inputs = [
        e["values"] for e in st["events"] if e["event"] == "input" and "tool_digital_output" in e["values"]
    ]
    assert tool_inputs[:3] == [
        {
            "input_int_register_23": tool_inputs[0]["input_int_register_23"],
            "tool_digital_output_mask": 1,
            "tool_digital_output": 1,
        },
        {
            "input_int_register_23": tool_inputs[1]["input_int_register_23"],
            "tool_digital_output_mask": 2,
            "tool_digital_output": 2,
        },
        {
            "input_int_register_23": tool_inputs[2]["input_int_register_23"],
            "tool_digital_output_mask": 1,
            "tool_digital_output": 0,
        },
    ]
    in_use = [e for e in st["events"] if e["event"] == "input_setup" and "IN_USE" in e["types"]]
    assert in_use and in_use[0]["recipe"] == 0


def test_dashboard_client(fake):
    fake.set(
        robot_model="UR3",
        protective_stop_unlock_delay_s=5.0,
        power_on_delay_s=0.05,
        brake_release_delay_s=0.05,
    )
    out = run_client(f"""
        import dashboard_client
        host = {fake.host!r}
        d = dashboard_client.DashboardClient(host)
        d.connect()
        res = dict(connected=d.isConnected(), model=d.getRobotModel(), remote=d.isInRemoteControl(),
                   version=d.polyscopeVersion(), serial=d.getSerialNumber(), robotmode=d.robotmode(),
                   safetymode=d.safetymode(), safetystatus=d.safetystatus(), program=d.programState())
        side(host, "set " + json.dumps({{"robot_model": "UR5", "safety_mode": 3}}))
        res["model2"] = d.getRobotModel()
        res["safetymode2"] = d.safetymode()
        try:
            d.unlockProtectiveStop()
            res["early_unlock"] = "ok"
        except Exception as exc:
            res["early_unlock"] = str(exc)
        side(host, "set " + json.dumps({{"protective_stop_unlock_delay_s": 0}}))
        d.unlockProtectiveStop()
        d.closeSafetyPopup()
        res["safetymode3"] = d.safetymode()
        d.powerOff(); res["off"] = d.robotmode()
        d.powerOn(); res["on"] = d.robotmode()
        until(lambda: d.robotmode() == "Robotmode: IDLE")
        d.brakeRelease()
        res["released"] = until(lambda: d.robotmode() == "Robotmode: RUNNING") is not None
        d.loadURP("/programs/pick.urp"); d.play(); res["running"] = d.running(); d.stop()
        d.send("frobnicate\\n"); res["unknown"] = d.receive()
        d.quit()
        d.disconnect()
        print(json.dumps(res))
    """)
    assert out["connected"] and out["model"] == "UR3" and out["remote"] is True
    assert out["version"] == "5.15.2.124036" and out["serial"] == "20235500001"
    assert out["robotmode"] == "Robotmode: RUNNING" and out["safetymode"] == "Safetymode: NORMAL"
    assert out["safetystatus"] == "Safetystatus: NORMAL" and out["program"] == "STOPPED <unnamed>"
    assert out["model2"] == "UR5" and out["safetymode2"] == "Safetymode: PROTECTIVE_STOP"
    assert out["early_unlock"].startswith(
        "Unlock protective stop failure: Cannot unlock protective stop until 5s"
    )
    assert out["safetymode3"] == "Safetymode: NORMAL"
    assert out["off"] == "Robotmode: POWER_OFF" and out["on"] == "Robotmode: POWER_ON" and out["released"]
    assert out["running"] is True
    assert out["unknown"] == "could not understand: 'frobnicate'"
    log = fake.state()["dashboard_log"]
    assert log[:3] == ["get robot model", "PolyscopeVersion", "is in remote control"]
    assert "quit" in log
    fake.set(robot_model="UR3", safety_mode=1, robot_mode=7)


def test_gripper_urcap_socket_session(fake):
    fake.set(gripper={"object_position": None, "activation_s": 0.05})
    with socket.create_connection((fake.host, 63352), timeout=3) as s:

        def ask(line: str) -> str:
            time.sleep(0.002)  # a client's polling pace; keeps the fake's command log short
            s.sendall(line.encode() + b"\n")
            return s.recv(1024).decode()

        assert ask("SET ACT 0") == "ack"  # 'ack' carries no newline: clients compare data == b'ack'
        assert ask("GET STA") == "STA 0\n"
        assert ask("SET ACT 1") == "ack"
        assert ask("GET STA") == "STA 1\n"  # activation in progress
        deadline = time.monotonic() + 2
        while ask("GET STA") != "STA 3\n":
            assert time.monotonic() < deadline
        assert ask("GET POS") == "POS 3\n"  # activation ends fully open
        assert ask("SET POS 200 SPE 255 FOR 100 GTO 1") == "ack"
        assert ask("GET PRE") == "PRE 200\n"
        seen = []
        while (obj := ask("GET OBJ")) == "OBJ 0\n":  # moving
            seen.append(int(ask("GET POS").split()[1]))
            assert time.monotonic() < deadline + 3
        assert obj == "OBJ 3\n" and ask("GET POS") == "POS 200\n"
        assert len(set(seen)) >= 3 and seen == sorted(seen)  # a finite speed: intermediate positions

        def wait_still() -> None:
            t0 = time.monotonic()
            while ask("GET OBJ") == "OBJ 0\n":
                assert time.monotonic() - t0 < 3

        assert ask("SET POS 0") == "ack"  # GTO is still 1: a new position starts a new motion
        wait_still()
        assert ask("GET POS") == "POS 3\n"  # clamped to the fully-open stop
        fake.set(gripper={"object_position": 120})
        assert ask("SET POS 255 GTO 1") == "ack"
        wait_still()
        assert ask("GET OBJ") == "OBJ 2\n" and ask("GET POS") == "POS 120\n"  # stopped on the object

        s.sendall(b"GET ACT\nGET GTO\nGET FLT\n")  # several requests in one write, as ur_rtde's getVars
        buf = b""
        while buf.count(b"\n") < 3:
            buf += s.recv(1024)
        assert buf == b"ACT 1\nGTO 1\nFLT 0\n"

        fake.set(safety_mode=7)  # tool power cut: values read as '?'
        assert ask("GET POS") == "POS ?\n"
        fake.set(safety_mode=1)
        assert ask("GET BOGUS") == "?\n"
    st = fake.state()
    assert {"command": "SET POS 200 SPE 255 FOR 100 GTO 1"}.items() <= next(
        e for e in st["gripper_log"] if e["command"].startswith("SET POS 200")
    ).items()
    assert st["gripper"]["POS"] == 120 and st["gripper"]["OBJ"] == 2


def test_raw_rtde_protocol_details(fake):
    """What ur_rtde never exercises: NOT_FOUND, IN_USE of a fieldbus, pause, recipe ids in data packages."""
    fake.set(fieldbus_inputs=["input_int_register_30"])

    def request(s, cmd: bytes, payload: bytes = b"") -> tuple[int, bytes]:
        s.sendall(struct.pack(">HB", len(payload) + 3, cmd[0]) + payload)
        while True:
            size, typ = struct.unpack(">HB", recv_exact(s, 3))
            body = recv_exact(s, size - 3)
            if typ != ord("U"):  # data packages may interleave with the reply after start
                return typ, body

    def recv_exact(s, n: int) -> bytes:
        out = b""
        while len(out) < n:
            out += s.recv(n - len(out))
        return out

    with socket.create_connection((fake.host, 30004), timeout=3) as s:
        assert request(s, b"V", struct.pack(">H", 3)) == (ord("V"), b"\x00")  # unknown protocol refused
        assert request(s, b"V", struct.pack(">H", 2)) == (ord("V"), b"\x01")
        typ, body = request(s, b"v")
        assert struct.unpack(">IIII", body) == (5, 15, 2, 124036)
        typ, body = request(s, b"O", struct.pack(">d", 125.0) + b"actual_q,no_such_field")
        assert body == b"\x00VECTOR6D,NOT_FOUND"
        typ, body = request(s, b"O", struct.pack(">d", 125.0) + b"timestamp,actual_q,robot_mode")
        assert body == b"\x01DOUBLE,VECTOR6D,INT32"
        typ, body = request(s, b"I", b"input_int_register_30,input_double_register_30")
        assert body == b"\x00IN_USE,DOUBLE"
        typ, body = request(s, b"I", b"input_int_register_31")
        assert body == b"\x01INT32"
        assert request(s, b"S") == (ord("S"), b"\x01")
        size, typ = struct.unpack(">HB", recv_exact(s, 3))
        packet = recv_exact(s, size - 3)
        assert typ == ord("U")
        rid, ts, *rest = struct.unpack(">Bd6di", packet)
        assert rid == 1 and ts > 0 and rest[-1] == 7
        s.sendall(struct.pack(">HBBi", 8, ord("U"), 1, 1234))  # input package for recipe 1
        assert request(s, b"P") == (ord("P"), b"\x01")
    st = fake.wait_for(lambda st: st["input_int_register_31"] == 1234)
    assert st["input_int_register_30"] == 0
    fake.set(fieldbus_inputs=[])


def test_side_channel_rejects_unknown_keys(fake):
    with pytest.raises(FakeControllerError, match="unknown state key"):
        fake.set(not_a_field=1)
    with pytest.raises(FakeControllerError, match="needs 6 numbers"):
        fake.set(actual_q=[0.0, 1.0])


def test_error_paths_refused_and_closed_connections():
    host = free_loopback_host()
    with start_fake_controller(host, servers=("rtde",), modes={"rtde": "refuse"}) as f:
        out = run_client(f"""
            import rtde_receive, dashboard_client
            res = {{}}
            t0 = time.monotonic()
            try:
                dashboard_client.DashboardClient({host!r}).connect()
                res["dashboard"] = "connected"
            except RuntimeError as exc:
                res["dashboard"] = str(exc)
            try:
                rtde_receive.RTDEReceiveInterface({host!r})
                res["rtde"] = "connected"
            except RuntimeError as exc:
                res["rtde"] = str(exc)
            res["elapsed"] = time.monotonic() - t0
            done(res)
        """)
        assert out["dashboard"] == "Timeout connecting to UR dashboard server."  # nothing on 29999
        assert out["rtde"] != "connected"  # accepted, then closed before the handshake
        assert out["elapsed"] < 3
        assert any(e["event"] == "refused" for e in f.state()["events"])
        with pytest.raises(OSError):
            socket.create_connection((host, 63352), timeout=1).close()


def test_two_fakes_side_by_side():
    with (
        start_fake_controller(None, robot_model="UR5", actual_q=[0.5] * 6) as a,
        start_fake_controller(None, robot_model="UR10", actual_q=[-0.5] * 6) as b,
    ):
        assert a.host != b.host
        out = run_client(f"""
            import rtde_receive, dashboard_client
            res = []
            for host in ({a.host!r}, {b.host!r}):
                d = dashboard_client.DashboardClient(host); d.connect()
                r = rtde_receive.RTDEReceiveInterface(host)
                res.append([d.getRobotModel(), r.getActualQ()])
            done(res)
        """)
        assert out == [["UR5", [0.5] * 6], ["UR10", [-0.5] * 6]]


def test_control_interface_fails_fast_without_script_port(fake):
    """RTDEControlInterface checks the dashboard, sets up RTDE, then uploads its script to port 30003.

    The fake does not run URScript; with its script sink off (the default) the upload is refused and the
    constructor raises at once instead of hanging.
    """
    fake.clear_logs()
    out = run_client(
        f"""
        import rtde_control
        t0 = time.monotonic()
        try:
            rtde_control.RTDEControlInterface({fake.host!r})
            res = "constructed"
        except RuntimeError as exc:
            res = str(exc)
        done(dict(res=res, elapsed=time.monotonic() - t0))
    """,
        timeout=20,
    )
    assert out["res"] == "connect: Connection refused" and out["elapsed"] < 2
    assert fake.state()["dashboard_log"] == [
        "PolyscopeVersion",
        "get serial number",
        "PolyscopeVersion",
        "is in remote control",
    ]


@pytest.mark.slow
def test_control_interface_times_out_on_unexecuted_script():
    """A controller that takes the script but never starts it: ur_rtde waits 5 s for PLAYING, then gives up."""
    with start_fake_controller(
        None, servers=("rtde", "dashboard", "script"), emulate_control_script=False
    ) as f:
        out = run_client(
            f"""
            import rtde_control
            t0 = time.monotonic()
            try:
                rtde_control.RTDEControlInterface({f.host!r})
                res = "constructed"
            except RuntimeError as exc:
                res = str(exc)
            print(json.dumps(dict(res=res, elapsed=time.monotonic() - t0)))
        """,
            timeout=30,
        )
        assert out["res"] == "ur_rtde: Failed to start control script, before timeout of 5 seconds"
        assert 4.5 < out["elapsed"] < 8
        st = f.state()
        assert st["scripts"][0].startswith("def rtde_control():")
        assert not st["control_script_running"] and st["program_state"] == "STOPPED"


def test_forward_kinematics_matches_ur3e_zero_pose():
    # All joints at zero: the arm lies stretched along -x; the wrist offsets set y and z.
    assert forward_kinematics([0.0] * 6, "UR3")[:3] == pytest.approx([-0.45675, -0.22315, 0.0665])


def test_side_channel_drops_connections_and_switches_servers(fake):
    with socket.create_connection((fake.host, 29999), timeout=2) as s:
        assert s.recv(1024) == b"Connected: Universal Robots Dashboard Server\n"
        assert fake.drop("dashboard") == {"dashboard": 1}
        assert s.recv(1024) == b""  # the controller went away mid-session
    fake.mode(dashboard="off")
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection((fake.host, 29999), timeout=2).close()
    fake.mode(dashboard="serve")
    with socket.create_connection((fake.host, 29999), timeout=2) as s:
        assert s.recv(1024).startswith(b"Connected")


# ---------------------------------------------------------------------------------------------------
# The control side: ur_rtde's rtde_control script, emulated by the fake at the RTDE register level
# ---------------------------------------------------------------------------------------------------
SERVO_ARGS = (
    "0.5, 0.5, 0.002, 0.1, 300"  # speed, acceleration, time, lookahead_time, gain (ur_rtde's examples)
)


@pytest.fixture(scope="module")
def _control_fake_module():
    with start_fake_controller(free_loopback_host(), servers=("rtde", "dashboard", "script")) as f:
        yield f


@pytest.fixture
def control_fake(_control_fake_module):
    """A fake with the realtime interface (30003) on: RTDEControlInterface's script runs there.

    Shared by the control tests, reset before each: no script running (a failed test may leave one, and
    a new RTDEControlInterface would first stop it), robot running, normal safety, empty logs.
    """
    fake = _control_fake_module
    fake.set(program_state="STOPPED", safety_mode=1, robot_mode=7, protective_stop_unlock_delay_s=5.0)
    fake.clear_logs()
    return fake


def test_control_interface_streams_servoj_and_the_arm_follows(control_fake):
    fake = control_fake
    q0 = [0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]
    fake.set(actual_q=q0)
    target = [q + d for q, d in zip(q0, (0.2, -0.1, 0.15, 0.05, -0.2, 0.3))]
    out = run_client(f"""
        import rtde_control, rtde_receive
        host, q0, target = {fake.host!r}, {q0!r}, {target!r}
        t0 = time.monotonic()
        c = rtde_control.RTDEControlInterface(host)
        res = dict(ctor_s=time.monotonic() - t0, running=c.isProgramRunning(), status=c.getRobotStatus(),
                   connected=c.isConnected(), fake=side(host, "get")["state"]["control_script_running"])
        r = rtde_receive.RTDEReceiveInterface(host)
        oks, seen = [], []
        t0 = time.monotonic()
        for i in range(500):  # 1 s at 500 Hz; the set point ramps to the target over 0.8 s, then holds
            t_start = c.initPeriod()
            a = min(1.0, (i + 1) / 400)
            oks.append(c.servoJ([x + (y - x) * a for x, y in zip(q0, target)], {SERVO_ARGS}))
            if i % 100 == 50:
                seen.append(r.getActualQ())
            c.waitPeriod(t_start)
        res.update(stream_s=time.monotonic() - t0, oks=sum(oks), seen=seen, at_end=r.getActualQ())
        res["settle_s"] = until(lambda: max(abs(x - y) for x, y in zip(r.getActualQ(), target)) < 1e-4, 2.0)
        res["stop"] = c.servoStop(2.0)  # returns once the script's stopl() is done: the arm is still
        time.sleep(0.01)  # the receive interface's own stream may be a cycle behind the control one
        held = r.getActualQ()
        time.sleep(0.05)
        res.update(held=held == r.getActualQ(), qd=r.getActualQd(), running_after=c.isProgramRunning())
        done(res)
    """)
    assert out["running"] and out["fake"] and out["connected"]
    assert out["status"] == 3  # robot_status_bits: power on | program running
    assert out["ctor_s"] < 2.0
    # Paced at 500 Hz (not a burst); the upper bound leaves room for overrun cycles on a loaded 2-core machine.
    assert out["oks"] == 500 and 0.95 < out["stream_s"] < 1.6
    # The arm moves with the stream (lagging the set point), reaches the held target, and stays after servoStop.
    firsts = [q[0] for q in out["seen"]]
    assert firsts == sorted(firsts) and q0[0] < firsts[0] < firsts[-1] < target[0]
    assert out["settle_s"] is not None
    assert out["stop"] is True and out["held"] and out["qd"] == [0.0] * 6 and out["running_after"]

    st = fake.state()
    servoj = [e for e in st["servo_log"] if e["cmd"] == "servoj"]
    assert st["servoj_count"] == len(servoj) == 500
    assert servoj[-1]["q"] == pytest.approx(target) and st["servo_target"] == pytest.approx(target)
    assert 0.9 < servoj[-1]["t"] - servoj[0]["t"] < 1.6  # streamed at 500 Hz, not in a burst
    assert st["servo_lookahead"] == 0.1 and st["servo_gain"] == 300 and st["servo_time"] == 0.002
    assert st["actual_q"] == pytest.approx(target, abs=1e-3)
    assert [e["cmd"] for e in st["servo_log"] if e["cmd"] != "servoj"] == ["script_start", "servo_stop"]
    assert next(e for e in st["servo_log"] if e["cmd"] == "servo_stop")["a"] == 2.0
    assert st["control_script_running"] and st["program_state"] == "PLAYING"  # os._exit: no stopScript

    # The next client finds that script still running: ur_rtde sends it the stop command, stops the program
    # through the dashboard, and uploads its own.
    out = run_client(f"""
        import rtde_control
        c = rtde_control.RTDEControlInterface({fake.host!r})
        done(dict(running=c.isProgramRunning(), teach=c.teachMode()))
    """)
    assert out == {"running": True, "teach": True}
    st = fake.state()
    assert st["control_script"]["starts"] == 2 and st["dashboard_log"][-1] == "stop"
    assert [e["cmd"] for e in st["servo_log"] if e["cmd"] != "servoj"][-4:] == [
        "stop_script",
        "script_end",
        "script_start",
        "teach_mode",
    ]


def test_control_interface_teach_mode_stop_script_and_disconnect(control_fake):
    """Teach mode holds nothing: the side channel moves the arm by hand. Upper-range registers (offset 24)."""
    fake = control_fake
    fake.set(actual_q=[0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
    hand_q = [0.3, -1.2, 1.4, -1.7, -1.5, 0.4]
    out = run_client(f"""
        import rtde_control, rtde_receive
        host = {fake.host!r}
        C = rtde_control.RTDEControlInterface
        c = C(host, 500.0, C.FLAG_UPLOAD_SCRIPT | C.FLAG_UPPER_RANGE_REGISTERS)
        r = rtde_receive.RTDEReceiveInterface(host)
        res = dict(teach=c.teachMode(), fake_teach=side(host, "get")["state"]["teach_mode"])
        side(host, "set " + json.dumps({{"actual_q": {hand_q!r}}}))  # an operator moves the arm
        res["seen_s"] = until(lambda: r.getActualQ() == {hand_q!r})
        time.sleep(0.05)
        res["still"] = r.getActualQ() == {hand_q!r}
        res["end"] = c.endTeachMode()
        time.sleep(0.02)
        res["after_end"] = r.getActualQ() == {hand_q!r}
        c.stopScript()
        until(lambda: r.getRuntimeState() == 1)  # the receive side sees the stop one RTDE frame later under load
        res.update(running=c.isProgramRunning(), runtime=r.getRuntimeState(), status=c.getRobotStatus())
        t0 = time.monotonic()
        c.disconnect()
        res.update(disconnect_s=time.monotonic() - t0, connected=c.isConnected())
        done(res)
    """)
    assert out["teach"] is True and out["fake_teach"] is True
    assert out["seen_s"] is not None and out["still"] and out["end"] is True and out["after_end"]
    assert out["running"] is False and out["runtime"] == 1 and out["status"] == 1
    assert out["connected"] is False and out["disconnect_s"] < 1.5
    st = fake.state()
    assert [e["cmd"] for e in st["servo_log"]] == [
        "script_start",
        "teach_mode",
        "end_teach_mode",
        "stop_script",
        "script_end",
    ]
    assert (
        st["control_script"]["register_offset"] == 24 and st["control_script"]["end_reason"] == "stop_script"
    )
    assert not st["control_script_running"] and not st["teach_mode"] and st["actual_q"] == hand_q
    commands = [
        e["values"]["input_int_register_24"]
        for e in st["events"]
        if e["event"] == "input" and "input_int_register_24" in e["values"]
    ]
    # The register handshake: clear, then each command followed by a clear once the script answered 'done'.
    assert commands == [0, 18, 0, 19, 0, 255, 0]


def test_protective_stop_during_servo_stream_ends_the_script(control_fake):
    fake = control_fake
    q0 = [0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]
    fake.set(actual_q=q0, protective_stop_unlock_delay_s=0.0)
    out = run_client(f"""
        import rtde_control, rtde_receive, dashboard_client
        host, q0 = {fake.host!r}, {q0!r}
        c = rtde_control.RTDEControlInterface(host)
        r = rtde_receive.RTDEReceiveInterface(host)
        oks, t_stop, q_stop = [], None, None
        for i in range(300):
            t_start = c.initPeriod()
            if i == 150:  # the arm hits something: the controller raises a protective stop
                side(host, "set " + json.dumps({{"safety_mode": 3}}))
                t_stop = time.monotonic()
            ok = c.servoJ([x + 0.0005 * i for x in q0], {SERVO_ARGS})
            oks.append(ok)
            if t_stop is not None and not ok and q_stop is None:
                res_first = (i, time.monotonic() - t_stop)
                time.sleep(0.01)  # the receive stream may be a cycle behind the control one
                q_stop = r.getActualQ()
            c.waitPeriod(t_start)
        time.sleep(0.05)
        res = dict(oks=oks, first_false=res_first, running=c.isProgramRunning(), status=c.getRobotStatus(),
                   connected=c.isConnected(), pstop=r.isProtectiveStopped(), runtime=r.getRuntimeState(),
                   safety=r.getSafetyMode(), held=r.getActualQ() == q_stop,
                   servo_stop=c.servoStop(), teach=c.teachMode())
        # Recovery as on a real arm: unlock through the dashboard, then upload the control script again.
        d = dashboard_client.DashboardClient(host); d.connect(); d.unlockProtectiveStop()
        res["reupload"] = c.reuploadScript()
        res["restart_s"] = until(c.isProgramRunning, 2.0)
        res["servo_again"] = c.servoJ(q0, {SERVO_ARGS})
        c.stopScript()
        done(res)
    """)
    oks = out["oks"]
    i_false, latency = out["first_false"]
    assert all(oks[:150]) and not any(oks[i_false:]) and 150 <= i_false <= 155 and latency < 0.05
    assert out["running"] is False and out["status"] == 1 and out["connected"] is True  # RTDE stays up
    assert out["pstop"] is True and out["runtime"] == 1 and out["safety"] == 3 and out["held"]
    assert out["servo_stop"] is False and out["teach"] is False  # every command: False, no exception
    assert out["reupload"] is True and out["restart_s"] is not None and out["servo_again"] is True
    st = fake.state()
    ends = [e for e in st["servo_log"] if e["cmd"] == "script_end"]
    assert [e["reason"] for e in ends] == ["safety mode PROTECTIVE_STOP", "stop_script"]
    recorded = [e for e in st["servo_log"] if e["cmd"] == "servoj"]
    before = [e for e in recorded if e["t"] < ends[0]["t"]]
    assert 150 <= len(before) <= i_false and len(recorded) == len(before) + 1  # nothing while stopped
    assert [e["cmd"] for e in st["servo_log"]].count("script_start") == 2
    assert st["control_script"]["starts"] >= 2 and not st["control_script_running"]


@pytest.mark.slow
def test_control_script_refused_while_protective_stopped():
    """The controller starts no program in a protective stop: ur_rtde's constructor times out after 5 s."""
    with start_fake_controller(None, servers=("rtde", "dashboard", "script"), safety_mode=3) as f:
        out = run_client(
            f"""
            import rtde_control
            try:
                rtde_control.RTDEControlInterface({f.host!r})
                res = "constructed"
            except RuntimeError as exc:
                res = str(exc)
            done(dict(res=res))
        """,
            timeout=30,
        )
        assert out["res"] == "ur_rtde: Failed to start control script, before timeout of 5 seconds"
        assert f.state()["servo_log"][-1] == {
            "t": pytest.approx(0, abs=60),
            "cmd": "script_refused",
            "reason": "safety mode PROTECTIVE_STOP",
        }
