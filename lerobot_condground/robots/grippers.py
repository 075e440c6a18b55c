"""Grippers on the UR3e's tool flange, used inside the arm's process.

- `RobotiqSocketGripper`: a Robotiq 2F-85 through the Robotiq URCap's socket on the controller (port
  63352), a line protocol: "SET POS 120" -> "ack", "GET POS" -> "POS 118".
- `DigitalOutputGripper`: a plain gripper switched by a tool digital output (RTDE IO interface).

Both take the command as closure 0 open .. 1 closed and report the measured closure the same way, the
convention of the simulation's `gripper.pos`.
"""

from __future__ import annotations

import socket
import threading
import time


class GripperError(ConnectionError):
    pass


class RobotiqSocketGripper:
    def __init__(self, host: str, port: int = 63352, speed: int = 128, force: int = 64, timeout: float = 2.0):
        for name, value in (("speed", speed), ("force", force)):
            if not 0 <= value <= 255:
                raise ValueError(f"Robotiq {name}={value}; allowed: 0..255")
        self.host, self.port, self.speed, self.force, self.timeout = host, port, speed, force, timeout
        self.sock: socket.socket | None = None
        self._io = threading.Lock()

    def _request(self, line: str) -> str:
        # The URCap answers a SET with a bare "ack" (no newline) and a GET with "NAME value\n".
        with self._io:
            self.sock.sendall(line.encode() + b"\n")
            reply = b""
            while not (reply.endswith(b"\n") or reply == b"ack"):
                chunk = self.sock.recv(1024)
                if not chunk:
                    raise GripperError(f"Robotiq URCap socket {self.host}:{self.port} closed the connection")
                reply += chunk
            return reply.decode().strip()

    def _set(self, **registers: int) -> None:
        line = "SET " + " ".join(f"{k} {v}" for k, v in registers.items())
        reply = self._request(line)
        if reply != "ack":
            raise GripperError(f"Robotiq answered {reply!r} to {line!r}")

    def _get(self, register: str) -> int:
        reply = self._request(f"GET {register}")
        name, _, value = reply.partition(" ")
        if name != register or not value.strip().lstrip("-").isdigit():
            raise GripperError(f"Robotiq answered {reply!r} to 'GET {register}'")
        return int(value)

    def connect(self, activate: bool = True, activation_timeout: float = 5.0) -> None:
        try:
            self.sock = socket.create_connection((self.host, self.port), timeout=self.timeout)
        except OSError as exc:
            raise GripperError(
                f"No Robotiq URCap socket at {self.host}:{self.port} ({exc}); is the Robotiq URCap installed and "
                "the gripper plugged in? Use --robot.gripper=digital_output or none for other grippers."
            ) from exc
        if not activate:  # dry run: read the fingers, never move them (activation opens and closes them)
            return
        if self._get("STA") != 3:  # 3 = activation complete
            self._set(ACT=0, ATR=0)
            self._set(ACT=1)
            deadline = time.monotonic() + activation_timeout
            while self._get("STA") != 3:
                if time.monotonic() > deadline:
                    raise GripperError(f"Robotiq did not finish activating within {activation_timeout} s")
                time.sleep(0.05)
        self._set(GTO=1, SPE=self.speed, FOR=self.force)

    def command(self, closure: float) -> None:
        self._set(POS=round(min(max(closure, 0.0), 1.0) * 255))

    def closure(self) -> float:
        return self._get("POS") / 255.0

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None


class DigitalOutputGripper:
    def __init__(self, host: str, output: int):
        if output not in (0, 1):
            raise ValueError(f"gripper_output={output}; a UR3e tool has digital outputs 0 and 1")
        self.host, self.output = host, output
        self.io = None

    def connect(self) -> None:
        import rtde_io

        self.io = rtde_io.RTDEIOInterface(self.host)

    def command(self, closure: float) -> None:
        self.io.setToolDigitalOut(self.output, closure > 0.5)

    def closure_from_bits(self, digital_output_bits: int) -> float:
        # Tool outputs are bits 16 and 17 of RTDE's actual_digital_output_bits.
        return float((digital_output_bits >> (16 + self.output)) & 1)

    def close(self) -> None:
        if self.io is not None:
            self.io.disconnect()
            self.io = None
