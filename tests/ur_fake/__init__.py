"""Test helpers around the fake UR e-Series controller in ``controller.py``.

``start_fake_controller(host, **state)`` runs the fake in a subprocess (``sys.executable``), waits until
every port listens, and returns a ``FakeController`` that talks to the fake's JSON side channel::

    with start_fake_controller(free_loopback_host(), actual_q=[0, -1.57, 1.57, -1.57, -1.57, 0]) as fake:
        rtde_r = rtde_receive.RTDEReceiveInterface(fake.host)   # in a subprocess: ur_rtde holds the GIL
        fake.set(safety_mode=3)                                  # protective stop, seen within a cycle
        assert fake.state()["tool_digital_outputs"] == [True, False]

With the realtime interface on (``servers=(..., "script")``) the fake also runs ur_rtde's control script, so
``rtde_control.RTDEControlInterface(fake.host)`` connects and servoJ / servoStop / teachMode / endTeachMode /
moveJ / stopScript work; ``state()`` then reports ``control_script_running``, ``teach_mode``, ``servo_target``
(and ``servo_lookahead``, ``servo_gain``, ``servo_time``, ``servo_speed``, ``servo_acceleration``),
``servoj_count`` and ``servo_log`` (the last 2000 of ``{"t", "cmd": "servoj", "q"}``, ``servo_stop``,
``teach_mode``, ``end_teach_mode``, ``stop_script``, ``script_start``, ``script_end`` with its reason...).
``set(safety_mode=3)`` ends the script as a protective stop does: every later command returns False.

The fake is a separate process on purpose: ur_rtde's native calls block every Python thread of the
process that makes them, so a fake living in the test process would stall under its own client.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .arm import forward_kinematics
from .servers import (
    CONTROL_PORT,
    DASHBOARD_PORT,
    DEFAULT_MODES,
    GRIPPER_PORT,
    RTDE_PORT,
    SCRIPT_PORT,
    SERVER_MODES,
    SERVERS,
)

CONTROLLER_SCRIPT = Path(__file__).with_name("controller.py")
PORTS = {
    "rtde": RTDE_PORT,
    "dashboard": DASHBOARD_PORT,
    "gripper": GRIPPER_PORT,
    "script": SCRIPT_PORT,
    "control": CONTROL_PORT,
}
DEFAULT_SERVERS = tuple(s for s in SERVERS if DEFAULT_MODES[s] != "off")

__all__ = [
    "FakeController",
    "FakeControllerError",
    "start_fake_controller",
    "free_loopback_host",
    "forward_kinematics",
    "PORTS",
    "SERVERS",
    "SERVER_MODES",
]


class FakeControllerError(RuntimeError):
    pass


def _address_free(host: str, ports) -> bool:
    for port in ports:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError:
            return False
        finally:
            s.close()
    return True


def free_loopback_host(ports=tuple(PORTS.values()), rng: random.Random | None = None) -> str:
    """A loopback address 127.0.0.2..254 on which all the fake's ports are free.

    Random rather than sequential so parallel test processes rarely race for the same address; a race
    that still happens fails the fake's bind, and ``start_fake_controller(None)`` then retries elsewhere.
    """
    rng = rng or random.Random(os.getpid() ^ time.monotonic_ns())
    candidates = list(range(2, 255))
    rng.shuffle(candidates)
    for last in candidates:
        host = f"127.0.0.{last}"
        if _address_free(host, ports):
            return host
    raise FakeControllerError("no loopback address 127.0.0.2..254 has the UR ports free")


class FakeController:
    """A running fake controller: its address, its process, and its side channel."""

    def __init__(self, host: str, proc: subprocess.Popen, ports: dict[str, int]):
        self.host = host
        self.proc = proc
        self.ports = ports
        self._sock: socket.socket | None = None
        self._buf = b""
        self._lock = threading.Lock()

    # ---- side channel ----------------------------------------------------------------------------
    def command(self, verb: str, arg: Any = None, timeout: float = 5.0) -> dict:
        """Sends one side-channel request and returns its JSON reply; raises on {"ok": false}."""
        line = verb if arg is None else f"{verb} {json.dumps(arg)}"
        with self._lock:
            if self._sock is None:
                self._sock = socket.create_connection((self.host, self.ports["control"]), timeout=timeout)
            self._sock.settimeout(timeout)
            self._sock.sendall(line.encode() + b"\n")
            while b"\n" not in self._buf:
                data = self._sock.recv(1 << 20)
                if not data:
                    self._sock.close()
                    self._sock = None
                    raise FakeControllerError(f"side channel closed during {verb!r}")
                self._buf += data
            reply, self._buf = self._buf.split(b"\n", 1)
        out = json.loads(reply)
        if not out.get("ok"):
            raise FakeControllerError(out.get("error", out))
        return out

    def set(self, **state) -> None:
        """Changes the robot's state: ``set(safety_mode=3)``, ``set(gripper={"object_position": 120})``."""
        self.command("set", state)

    def state(self) -> dict:
        """Everything: RTDE values, dashboard state, gripper registers, and the logs of what clients did."""
        return self.command("get")["state"]

    def mode(self, **modes: str) -> None:
        """Per-server behaviour for new connections: serve, refuse, silent, or off (not listening)."""
        self.command("mode", modes)

    def drop(self, *servers: str) -> dict:
        """Closes the current client connections of these servers (all of them when none are named)."""
        return self.command("drop", {"servers": list(servers or SERVERS)})["dropped"]

    def clear_logs(self) -> None:
        self.command("clear")

    def wait_for(
        self, predicate: Callable[[dict], bool], timeout: float = 2.0, interval: float = 0.01
    ) -> dict:
        """Polls ``state()`` until ``predicate(state)`` holds; returns that state or raises TimeoutError."""
        deadline = time.monotonic() + timeout
        while True:
            st = self.state()
            if predicate(st):
                return st
            if time.monotonic() > deadline:
                raise TimeoutError(f"fake controller state did not satisfy {predicate} within {timeout}s")
            time.sleep(interval)

    # ---- lifecycle -------------------------------------------------------------------------------
    def stop(self, timeout: float = 3.0) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(OSError, FakeControllerError, ValueError):
                self.command("quit", timeout=1.0)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout)
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        for stream in (self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()

    def __enter__(self) -> FakeController:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def __repr__(self) -> str:
        return f"FakeController(host={self.host!r}, pid={self.proc.pid})"


def start_fake_controller(
    host: str | None = None,
    *,
    servers=DEFAULT_SERVERS,
    modes: dict[str, str] | None = None,
    startup_timeout: float = 10.0,
    verbose: bool = False,
    extra_args=(),
    **initial_state,
) -> FakeController:
    """Starts the fake on ``host`` (None: a free loopback address, retried on a lost race).

    ``servers``: which of rtde/dashboard/gripper/script listen (the others refuse connections; the realtime
    interface on 30003, which records URScript and runs ur_rtde's control script, is off by default, so
    RTDEControlInterface fails at once unless a test asks for it); ``modes``: initial per-server modes
    (serve, refuse, silent, off), applied after ``servers``; ``initial_state``: any key the side
    channel's ``set`` takes (``robot_model="UR5"``, ``safety_mode=3``, ``gripper={...}``).
    """
    attempts = 5 if host is None else 1
    last_error = ""
    for _ in range(attempts):
        h = host or free_loopback_host()
        cmd = [
            sys.executable,
            str(CONTROLLER_SCRIPT),
            "--host",
            h,
            "--exit-with-parent",
            "--state",
            json.dumps(initial_state),
        ]
        cmd += [f"--no-{s}" for s in SERVERS if s not in servers]
        cmd += [f"--mode={s}=serve" for s in servers if DEFAULT_MODES[s] == "off"]
        cmd += [f"--mode={s}={m}" for s, m in (modes or {}).items()]
        cmd += ["--verbose"] if verbose else []
        cmd += list(extra_args)
        proc = subprocess.Popen(
            cmd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=None if verbose else subprocess.PIPE,
            text=True,
        )
        ready = _wait_ready(proc, startup_timeout)
        if ready is not None:
            fake = FakeController(h, proc, ready["ports"])
            fake.command("ping")
            return fake
        proc.kill()
        out, err = proc.communicate(timeout=5)
        last_error = f"{out}\n{err}"
        if host is not None:
            break
    raise FakeControllerError(f"fake controller did not start: {last_error.strip()}")


def _wait_ready(proc: subprocess.Popen, timeout: float) -> dict | None:
    """Reads the fake's stdout until its READY line (printed after every listen()) or failure."""
    result: list[dict | None] = [None]

    def read() -> None:
        for line in proc.stdout:
            if line.startswith("READY "):
                result[0] = json.loads(line[len("READY ") :])
                return
            if line.startswith("FAILED"):
                return

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(timeout)
    return result[0]
