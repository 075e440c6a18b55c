"""The Robotiq URCap socket (port 63352): "SET ACT 1" / "GET POS" text in front of a 2F-85 whose finger
moves at a finite speed and can stop on an object."""

from __future__ import annotations

import math
import socket
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .state import Controller


class Gripper:
    """Robotiq 2F-85 as the URCap socket exposes it (register names of the Robotiq manual)."""

    REGISTERS = (
        "ACT",
        "GTO",
        "ATR",
        "ARD",
        "MOD",
        "FOR",
        "SPE",
        "POS",
        "STA",
        "PRE",
        "OBJ",
        "FLT",
        "LBP",
        "LRD",
        "LBL",
        "LGN",
        "MSC",
        "PID",
    )
    CONFIG_DEFAULTS = {
        "position": 3.0,  # device units, 0 open .. 255 closed
        "min_position": 3,  # a real 2F-85 reads ~3 fully open and ~230 fully closed on nothing
        "max_position": 230,
        "object_position": None,  # closing stops here with OBJ 2 (an object between the fingers)
        "outer_object_position": None,  # opening stops here with OBJ 1
        "activation_s": 0.3,
        "stroke_mm": 85.0,
        "min_speed_mm_s": 20.0,
        "max_speed_mm_s": 150.0,
    }

    def __init__(self):
        self.regs = dict.fromkeys(self.REGISTERS, 0)
        self.config = dict(self.CONFIG_DEFAULTS)
        self.activation_done_at = None
        self.moving = False
        self.last_t = time.monotonic()

    def speed_units_s(self) -> float:
        c = self.config
        mm_s = c["min_speed_mm_s"] + (c["max_speed_mm_s"] - c["min_speed_mm_s"]) * self.regs["SPE"] / 255
        return mm_s * 255.0 / c["stroke_mm"]

    def advance(self, now: float, frozen: bool) -> None:
        dt, self.last_t = now - self.last_t, now
        if frozen:  # tool power cut (emergency stop): nothing moves
            return
        if self.regs["STA"] == 1 and self.activation_done_at is not None and now >= self.activation_done_at:
            self.regs["STA"] = 3  # activation completes with the fingers fully open
            self.config["position"] = float(self.config["min_position"])
            self.activation_done_at = None
        if not self.moving:
            return
        c, pos = self.config, self.config["position"]
        goal = float(min(max(self.regs["PRE"], c["min_position"]), c["max_position"]))
        stop, stop_obj = goal, 3
        if goal > pos and c["object_position"] is not None and pos <= c["object_position"] < goal:
            stop, stop_obj = float(c["object_position"]), 2
        elif (
            goal < pos and c["outer_object_position"] is not None and goal < c["outer_object_position"] <= pos
        ):
            stop, stop_obj = float(c["outer_object_position"]), 1
        step = self.speed_units_s() * dt
        if abs(stop - pos) <= step:
            c["position"] = stop
            self.moving = False
            self.regs["OBJ"] = stop_obj
        else:
            c["position"] = pos + math.copysign(step, stop - pos)

    def get(self, name: str) -> int | None:
        if name == "POS":
            return int(round(self.config["position"]))
        return self.regs.get(name)

    def set(self, pairs: list[tuple[str, int]], now: float) -> None:
        changed = dict(pairs)
        was_act = self.regs["ACT"]
        for name, value in pairs:
            if name != "POS":
                self.regs[name] = max(0, min(255, value))
        if "ACT" in changed:
            if was_act == 0 and self.regs["ACT"] == 1:
                self.regs["STA"] = 1
                self.regs["FLT"] = 0
                self.activation_done_at = now + self.config["activation_s"]
            elif self.regs["ACT"] == 0:  # reset: deactivates and clears faults
                self.regs.update(STA=0, OBJ=0, FLT=0, GTO=0)
                self.moving = False
                self.activation_done_at = None
        if "POS" in changed:
            self.regs["POS"] = max(0, min(255, changed["POS"]))
        if "GTO" in changed or "POS" in changed:
            if self.regs["GTO"] == 1:
                if self.regs["ACT"] == 0:
                    self.regs["FLT"] = 7  # "the activation bit must be set prior to action"
                elif self.regs["STA"] != 3:
                    self.regs["FLT"] = 5  # "action delayed, activation must be completed"
                else:
                    self.regs["PRE"] = self.regs["POS"]  # echo of the requested position
                    self.regs["OBJ"] = 0
                    self.moving = True
            else:
                self.moving = False

    def snapshot(self) -> dict:
        out = {name: self.get(name) for name in self.REGISTERS}
        out.update(self.config)
        out["moving"] = self.moving
        return out


def gripper_command(ctl: Controller, line: str) -> str:
    """One URCap request line -> reply (no newline after 'ack', a newline after 'VAR value')."""
    text = line.strip()
    tokens = text.split()
    with ctl.lock:
        now = time.monotonic()
        ctl.gripper_log.append({"t": round(ctl.now(), 4), "command": text})
        g = ctl.gripper
        g.advance(now, ctl.gripper_frozen())
        if len(tokens) == 2 and tokens[0] == "GET":
            name = tokens[1]
            if name not in g.REGISTERS:
                return "?\n"
            if ctl.gripper_frozen():  # tool power off: the URCap answers a question mark
                return f"{name} ?\n"
            return f"{name} {g.get(name)}\n"
        if tokens and tokens[0] == "SET" and len(tokens) >= 3 and len(tokens) % 2 == 1:
            pairs = []
            for name, value in zip(tokens[1::2], tokens[2::2]):
                if name not in g.REGISTERS:
                    return "?"
                try:
                    pairs.append((name, int(value)))
                except ValueError:
                    return "?"
            g.set(pairs, now)
            g.advance(now, ctl.gripper_frozen())
            return "ack"
        return "?"


def serve_gripper(ctl: Controller, conn: socket.socket, peer) -> None:
    ctl.log("gripper", "connect", peer=f"{peer[0]}:{peer[1]}")
    buf = b""
    while True:
        data = conn.recv(4096)
        if not data:
            break
        buf += data
        replies = []
        # Several requests in one segment (ur_rtde's getVars sends "GET A\nGET B\n") get one reply each,
        # written together.
        while b"\n" in buf:
            line, buf = buf.split(b"\n", 1)
            if line.strip():
                replies.append(gripper_command(ctl, line.decode("utf-8", "replace")))
        if replies:
            conn.sendall("".join(replies).encode())
    ctl.log("gripper", "disconnect", peer=f"{peer[0]}:{peer[1]}")
