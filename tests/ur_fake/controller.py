#!/usr/bin/env python3
"""A loopback fake of a UR e-Series controller, faithful at the protocol boundary.

It serves, on one loopback address, what the plugin's UR3e path talks to:

* RTDE (port 30004): the binary "Real-Time Data Exchange" protocol, versions 1 and 2 (ur_rtde speaks 2);
* the dashboard server (port 29999): the one-line text protocol;
* the Robotiq URCap socket (port 63352): "SET ACT 1" / "GET POS" text, with a finger that moves at a
  finite speed and can stop on an object;
* the realtime interface (port 30003, off unless asked for): records the URScript clients send and runs
  ur_rtde's rtde_control script the way the controller would, at the level of the RTDE registers it
  talks through (servoJ, servoStop, teach mode, moveJ, stopScript; see ControlScript), with an arm whose
  joints follow the commands and a protective stop that ends the script;
* a control side channel (port 30099): line-based JSON so a test can change the robot's state while real
  clients are connected and read back what the clients did.

The real ports are fixed (ur_rtde's RTDE clients take no port), so several fakes run side by side on
distinct addresses 127.0.0.2..127.0.0.254. Stdlib only: one thread per connection keeps each protocol
handler a plain blocking loop, which is what the real servers look like from the client side.

Run: ``python tests/ur_fake/controller.py --host 127.0.0.7`` (or ``PYTHONPATH=tests python -m
ur_fake.controller ...``). ``python -m tests.ur_fake.controller`` does not work in this venv: draccus
installs a top-level ``tests`` package into site-packages, and a regular package there wins over the
repository's ``tests/`` directory, which has no ``__init__.py``. It prints ``READY {...}`` on stdout once
every port is listening.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import os
import re
import signal
import socket
import struct
import sys
import threading
import time

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
GRIPPER_PORT = 63352
SCRIPT_PORT = 30003  # the realtime interface, where ur_rtde's RTDEControlInterface uploads its script
CONTROL_PORT = 30099
SERVERS = ("rtde", "dashboard", "gripper", "script")
# The script port is off unless asked for, so by default RTDEControlInterface fails at once (connection
# refused) and the plugin's dry-run tests never start a control script. With it on, the fake records what
# arrives and runs ur_rtde's control script (ControlScript below), as a controller would.
DEFAULT_MODES = {"rtde": "serve", "dashboard": "serve", "gripper": "serve", "script": "off"}
# "serve": normal; "refuse": accept then close at once (client sees EOF); "silent": accept, read and
# never answer (client times out); "off": not listening (connection refused).
SERVER_MODES = ("serve", "refuse", "silent", "off")

# ---------------------------------------------------------------------------------------------------
# RTDE protocol tables
# ---------------------------------------------------------------------------------------------------
RTDE_REQUEST_PROTOCOL_VERSION = ord("V")
RTDE_GET_URCONTROL_VERSION = ord("v")
RTDE_TEXT_MESSAGE = ord("M")
RTDE_DATA_PACKAGE = ord("U")
RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
RTDE_CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
RTDE_CONTROL_PACKAGE_START = ord("S")
RTDE_CONTROL_PACKAGE_PAUSE = ord("P")
RTDE_MAX_FREQUENCY = 500.0  # e-Series real-time loop
RTDE_V1_FREQUENCY = 125.0  # protocol 1 has no frequency field; CB3 rate

# Big-endian struct codes of the RTDE types (the guide: network byte order throughout).
TYPE_FORMATS = {
    "BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
    "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I",
}
TYPE_LENGTHS = {"VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}


def _output_types() -> dict[str, str]:
    """Output fields of the RTDE guide (e-Series 5.x), name -> type."""
    v6, v3, d = "VECTOR6D", "VECTOR3D", "DOUBLE"
    t = {
        "timestamp": d,
        "target_q": v6, "target_qd": v6, "target_qdd": v6, "target_current": v6, "target_moment": v6,
        "actual_q": v6, "actual_qd": v6, "actual_current": v6, "actual_current_window": v6,
        "joint_control_output": v6,
        "actual_TCP_pose": v6, "actual_TCP_speed": v6, "actual_TCP_force": v6,
        "target_TCP_pose": v6, "target_TCP_speed": v6,
        "actual_digital_input_bits": "UINT64", "joint_temperatures": v6, "actual_execution_time": d,
        "robot_mode": "INT32", "joint_mode": "VECTOR6INT32", "safety_mode": "INT32", "safety_status": "INT32",
        "actual_tool_accelerometer": v3, "speed_scaling": d, "target_speed_fraction": d,
        "actual_momentum": d, "actual_main_voltage": d, "actual_robot_voltage": d, "actual_robot_current": d,
        "actual_joint_voltage": v6, "actual_digital_output_bits": "UINT64", "runtime_state": "UINT32",
        "elbow_position": v3, "elbow_velocity": v3,
        "robot_status_bits": "UINT32", "safety_status_bits": "UINT32", "analog_io_types": "UINT32",
        "standard_analog_input0": d, "standard_analog_input1": d,
        "standard_analog_output0": d, "standard_analog_output1": d, "io_current": d,
        "euromap67_input_bits": "UINT32", "euromap67_output_bits": "UINT32",
        "euromap67_24V_voltage": d, "euromap67_24V_current": d,
        "tool_mode": "UINT32", "tool_analog_input_types": "UINT32",
        "tool_analog_input0": d, "tool_analog_input1": d, "tool_output_voltage": "INT32",
        "tool_output_current": d, "tool_temperature": d, "tcp_force_scalar": d,
        "output_bit_registers0_to_31": "UINT32", "output_bit_registers32_to_63": "UINT32",
        "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
        "tool_output_mode": "UINT8", "tool_digital_output0_mode": "UINT8", "tool_digital_output1_mode": "UINT8",
        "payload": d, "payload_cog": v3, "payload_inertia": v6, "script_control_line": "UINT32",
        "ft_raw_wrench": v6, "joint_position_deviation_ratio": d, "collision_detection_ratio": d,
        "time_scale_source": "UINT32", "actual_current_as_torque": v6,
    }
    for i in range(64, 128):
        t[f"output_bit_register_{i}"] = "BOOL"
        t[f"input_bit_register_{i}"] = "BOOL"
    for i in range(48):
        t[f"output_int_register_{i}"] = "INT32"
        t[f"output_double_register_{i}"] = d
        t[f"input_int_register_{i}"] = "INT32"  # inputs can be read back as outputs
        t[f"input_double_register_{i}"] = d
    return t


def _input_types() -> dict[str, str]:
    """Input fields of the RTDE guide, name -> type."""
    t = {
        "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
        "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
        "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
        "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
        "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
        "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
        "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
        "external_force_torque": "VECTOR6D",
    }
    for i in range(64, 128):
        t[f"input_bit_register_{i}"] = "BOOL"
    for i in range(48):
        t[f"input_int_register_{i}"] = "INT32"
        t[f"input_double_register_{i}"] = "DOUBLE"
    return t


OUTPUT_TYPES = _output_types()
INPUT_TYPES = _input_types()
# Fields newer than early e-Series software: a controller older than this answers NOT_FOUND, as the real
# one does (ur_rtde gates these on the version it reads with 'v').
OUTPUT_MIN_VERSION = {"ft_raw_wrench": (5, 9), "actual_current_as_torque": (5, 23)}

ROBOT_MODES = {
    -1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
    4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE",
}
SAFETY_MODES = {
    1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
    6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT",
    10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE", 12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
    13: "SYSTEM_THREE_POSITION_ENABLING_STOP",
}
RUNTIME_STATES = {"STOPPING": 0, "STOPPED": 1, "PLAYING": 2, "PAUSING": 3, "PAUSED": 4, "RESUMING": 5}
EMERGENCY_STOPS = (6, 7)

# e-Series DH parameters (Universal Robots' published kinematics), so actual_TCP_pose agrees with actual_q.
DH = {
    "UR3": ([0.15185, 0, 0, 0.13105, 0.08535, 0.0921], [0, -0.24355, -0.2132, 0, 0, 0]),
    "UR5": ([0.1625, 0, 0, 0.1333, 0.0997, 0.0996], [0, -0.425, -0.3922, 0, 0, 0]),
    "UR10": ([0.1807, 0, 0, 0.17415, 0.11985, 0.11655], [0, -0.6127, -0.57155, 0, 0, 0]),
    "UR16": ([0.1807, 0, 0, 0.17415, 0.11985, 0.11655], [0, -0.4784, -0.36, 0, 0, 0]),
}
DH_ALPHA = [math.pi / 2, 0, 0, math.pi / 2, -math.pi / 2, 0]


def _matmul(a, b):
    return [[sum(a[i][k] * b[k][j] for k in range(4)) for j in range(4)] for i in range(4)]


def _rotvec_to_matrix(rx, ry, rz):
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle < 1e-12:
        return [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    x, y, z = rx / angle, ry / angle, rz / angle
    c, s, C = math.cos(angle), math.sin(angle), 1 - math.cos(angle)
    return [
        [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
        [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
        [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
    ]


def _matrix_to_rotvec(r):
    cos_a = max(-1.0, min(1.0, (r[0][0] + r[1][1] + r[2][2] - 1) / 2))
    angle = math.acos(cos_a)
    if angle < 1e-9:
        return [0.0, 0.0, 0.0]
    if math.pi - angle < 1e-6:  # axis from the diagonal; sin(angle) is ~0
        x = math.sqrt(max(0.0, (r[0][0] + 1) / 2))
        y = math.copysign(math.sqrt(max(0.0, (r[1][1] + 1) / 2)), r[0][1] if x > 1e-6 else 1.0)
        z = math.copysign(math.sqrt(max(0.0, (r[2][2] + 1) / 2)), r[0][2] if x > 1e-6 else r[1][2])
        return [x * angle, y * angle, z * angle]
    k = angle / (2 * math.sin(angle))
    return [(r[2][1] - r[1][2]) * k, (r[0][2] - r[2][0]) * k, (r[1][0] - r[0][1]) * k]


def forward_kinematics(q, model: str = "UR3", tcp_offset=(0, 0, 0, 0, 0, 0)) -> list[float]:
    """TCP pose [x, y, z, rx, ry, rz] (base frame, rotation vector) as the controller reports it."""
    d, a = DH.get(model.upper().rstrip("E"), DH["UR3"])
    t = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
    for i in range(6):
        ct, st = math.cos(q[i]), math.sin(q[i])
        ca, sa = math.cos(DH_ALPHA[i]), math.sin(DH_ALPHA[i])
        t = _matmul(t, [[ct, -st * ca, st * sa, a[i] * ct], [st, ct * ca, -ct * sa, a[i] * st],
                        [0, sa, ca, d[i]], [0, 0, 0, 1]])
    r = _rotvec_to_matrix(*tcp_offset[3:])
    tool = [r[0] + [tcp_offset[0]], r[1] + [tcp_offset[1]], r[2] + [tcp_offset[2]], [0, 0, 0, 1]]
    t = _matmul(t, tool)
    return [t[0][3], t[1][3], t[2][3]] + _matrix_to_rotvec([row[:3] for row in t[:3]])


# ---------------------------------------------------------------------------------------------------
# Robot state
# ---------------------------------------------------------------------------------------------------
HOME_Q = [0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]

# Non-RTDE keys of the state (the controller's own bookkeeping, dashboard and timing knobs).
META_DEFAULTS = {
    "robot_model": "UR3",
    "serial_number": "20235500001",
    "software_version": "5.15.2.124036",  # PolyScope / URControl; RTDE 'v' reports its first four fields
    "software_build_date": "Apr 16 2024",
    "is_in_remote_control": True,
    "operational_mode": "AUTOMATIC",
    "loaded_program": None,
    "known_programs": None,  # None: any 'load X' succeeds; a list: only those exist
    "program_state": "STOPPED",  # STOPPED, PLAYING, PAUSED (dashboard programState; runtime_state follows)
    "program_saved": True,
    "tcp_offset": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    "protective_stop_unlock_delay_s": 5.0,  # the controller refuses unlocking earlier than 5 s
    "power_on_delay_s": 0.3,  # POWER_ON -> IDLE after 'power on'
    "brake_release_delay_s": 0.3,  # IDLE -> RUNNING after 'brake release'
    "fieldbus_inputs": [],  # input names held by EtherNet/IP, PROFINET, MODBUS: RTDE answers IN_USE
    "max_rtde_frequency": RTDE_MAX_FREQUENCY,
    # Run ur_rtde's control script when it arrives on port 30003 (False: only record it, as a controller
    # that never starts it, so RTDEControlInterface times out after 5 s).
    "emulate_control_script": True,
}

# RTDE outputs whose value, unless a test sets it, follows other state (None in the store = derived).
DERIVED = ("timestamp", "target_q", "actual_TCP_pose", "target_TCP_pose", "robot_status_bits",
           "safety_status_bits", "safety_status", "runtime_state", "speed_scaling")


def _rtde_defaults() -> dict:
    """Plausible idle values for every RTDE output (a UR3e powered, brakes released, at rest)."""
    values = {}
    for name, typ in OUTPUT_TYPES.items():
        n = TYPE_LENGTHS.get(typ)
        values[name] = [0.0 if typ.endswith("D") else 0] * n if n else (False if typ == "BOOL" else 0)
        if typ in ("DOUBLE",):
            values[name] = 0.0
    values.update({
        "actual_q": list(HOME_Q), "joint_temperatures": [31.2, 32.0, 31.6, 33.1, 33.4, 32.8],
        "actual_execution_time": 0.12, "robot_mode": 7, "safety_mode": 1, "joint_mode": [253] * 6,
        "actual_tool_accelerometer": [0.0, 0.0, 9.81], "target_speed_fraction": 1.0,
        "actual_main_voltage": 48.1, "actual_robot_voltage": 47.9, "actual_robot_current": 0.45,
        "actual_joint_voltage": [47.8, 47.7, 47.8, 47.9, 47.8, 47.8], "tool_mode": 253,
        "tool_output_voltage": 24, "tool_temperature": 34.5, "io_current": 0.08, "payload": 0.9,
        "payload_cog": [0.0, 0.0, 0.06], "elbow_position": [0.0, 0.0, 0.0],
        "actual_current": [0.01, -1.2, -0.6, 0.05, 0.02, 0.0],
    })
    values["external_force_torque"] = [0.0] * 6  # an input only; kept so 'get' shows what clients wrote
    for name in DERIVED:
        values[name] = None
    return values


class StateError(ValueError):
    pass


class Gripper:
    """Robotiq 2F-85 as the URCap socket exposes it (register names of the Robotiq manual)."""

    REGISTERS = ("ACT", "GTO", "ATR", "ARD", "MOD", "FOR", "SPE", "POS", "STA", "PRE", "OBJ", "FLT",
                 "LBP", "LRD", "LBL", "LGN", "MSC", "PID")
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
        self.regs = {name: 0 for name in self.REGISTERS}
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
        elif goal < pos and c["outer_object_position"] is not None and goal < c["outer_object_position"] <= pos:
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


# ---------------------------------------------------------------------------------------------------
# ur_rtde's control script, emulated at the RTDE register level
# ---------------------------------------------------------------------------------------------------
# RTDEControlInterface uploads rtde_control.script to port 30003 and talks to it only through RTDE
# registers (offset 0, or 24 with FLAG_UPPER_RANGE_REGISTERS):
#   input_int_register_0       command id (0 = none); input_int_register_1 the 'async' flag
#   input_double_register_0..  arguments (servoJ: q 0-5, speed 6, acceleration 7, time 8, lookahead 9, gain 10)
#   output_int_register_0      script -> client: 1 ready for a command, 2 done with the command
#   output_int_register_2      async operation progress
# and detects "the script runs" by runtime_state == PLAYING (isProgramRunning), nothing else.
CMD_NONE, CMD_MOVEJ, CMD_SERVOJ, CMD_SPEED_STOP, CMD_SERVO_STOP = 0, 1, 11, 15, 16
CMD_TEACH_MODE, CMD_END_TEACH_MODE, CMD_PROTECTIVE_STOP = 18, 19, 31
CMD_STOPL, CMD_STOPJ, CMD_STOP_SCRIPT = 33, 34, 255
# Commands the script's main loop treats as "realtime": processed every cycle while the register holds
# them and answered with "ready", never "done" (the client does not wait for them). Read from the
# uploaded script when it has the line; this is the list of ur_rtde 1.6.
REALTIME_CMDS = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
SCRIPT_READY, SCRIPT_DONE = 1, 2
CMD_NAMES = {CMD_MOVEJ: "movej", CMD_SERVOJ: "servoj", CMD_SPEED_STOP: "speed_stop", CMD_SERVO_STOP: "servo_stop",
             CMD_TEACH_MODE: "teach_mode", CMD_END_TEACH_MODE: "end_teach_mode",
             CMD_PROTECTIVE_STOP: "protective_stop", CMD_STOPL: "stopl", CMD_STOPJ: "stopj",
             CMD_STOP_SCRIPT: "stop_script"}
# e-Series joint speed limits (base/shoulder/elbow 180 deg/s, wrists 360 deg/s): servoj cannot outrun them.
MAX_JOINT_SPEED = [math.pi] * 3 + [2 * math.pi] * 3
SERVO_LOG_LEN = 2000
# Safety modes in which the controller runs programs; any other one stops the control script.
RUNNABLE_SAFETY = (1, 2)


def parse_program(text: str) -> dict:
    """What the fake needs from an uploaded URScript program: its name, whether it is ur_rtde's control
    script, that script's register offset and its realtime command list."""
    m = re.match(r"\s*(?:def|sec)\s+(\w+)\s*\(", text)
    info = {"name": m.group(1) if m else None, "control": False, "offset": 0, "realtime": REALTIME_CMDS}
    # ur_rtde injects the offset after a comment: "global reg_offset_int = # int register offset\n0".
    off = re.search(r"global\s+reg_offset_int\s*=\s*(?:#[^\n]*\n)?\s*(\d+)", text)
    info["control"] = bool(m and "signal_ready()" in text and "read_input_integer_reg(0)" in text)
    if off:
        info["offset"] = int(off.group(1))
    rt = re.search(r"if\s+((?:cmd\s*==\s*\d+\s*(?:or\s+)?)+):\s*\n\s*# for realtime commands", text)
    if rt:
        info["realtime"] = frozenset(int(n) for n in re.findall(r"\d+", rt.group(1)))
    return info


class ControlScript:
    """The running rtde_control.script: its main loop, the commands the plugin uses, and the arm's motion.

    Lazy rather than a 500 Hz thread: ``advance(now)`` runs the script's loop body and integrates the
    motion up to ``now``, and it is called whenever anything observes or changes the state (every RTDE
    output package, every input package, the side channel, the dashboard). Results are the same as a
    loop polled every cycle, without a third busy thread in a fake that shares 2 cores with its client.
    The caller holds the controller lock.
    """

    def __init__(self, ctl: "Controller"):
        self.ctl = ctl
        self.running = False
        self.offset = 0
        self.realtime = REALTIME_CMDS
        self.executing = False  # the script's 'executing_cmd': a non-realtime command was taken
        self.busy = None  # None, "stop" or "move": the main loop is blocked in stopl/stopj/movej
        self.busy_signals_done = False  # a synchronous command answers 'done' once its motion ends
        self.stop_decel = 10.0
        self.motion = None  # None, "servo", "stop", "move": what moves the joints
        self.teach_mode = False
        self.servo = {"target": None, "speed": 0.0, "acceleration": 0.0, "time": 0.002, "lookahead": 0.1,
                      "gain": 300.0}
        self.move_target, self.move_speed = None, 1.05
        self.qd = [0.0] * 6
        self.last_t = time.monotonic()
        self.log = collections.deque(maxlen=SERVO_LOG_LEN)
        self.async_wr_count = 0
        self.async_op_id = 0
        self.last_cmd = 0
        self.end_reason = None
        self.starts = 0

    # ---- registers ---------------------------------------------------------------------------------
    def _in_int(self, i: int) -> int:
        return int(self.ctl.state[f"input_int_register_{i + self.offset}"])

    def _in_double(self, i: int) -> float:
        return float(self.ctl.state[f"input_double_register_{i + self.offset}"])

    def _out_int(self, i: int, value: int) -> None:
        self.ctl.state[f"output_int_register_{i + self.offset}"] = int(value)

    def _record(self, cmd: str, **data) -> None:
        self.log.append({"t": round(self.ctl.now(), 6), "cmd": cmd, **data})

    def _async_progress(self, value: int) -> None:
        """The script's write_async_progress_register: change count in bits 16-23, operation id in 24-30,
        bit 15 'running' and the progress in bits 0-14 while an operation runs."""
        self.async_wr_count = (self.async_wr_count + 1) % 128
        if value == 0:
            self.async_op_id = (self.async_op_id + 1) % 128
        reg = self.async_wr_count * 65536 + self.async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self._out_int(2, reg)

    # ---- lifecycle ---------------------------------------------------------------------------------
    def program_received(self, text: str) -> None:
        """A complete program arrived on port 30003: a real controller stops what runs and starts it."""
        ctl, s = self.ctl, self.ctl.state
        info = parse_program(text)
        if not s["emulate_control_script"]:
            ctl.log("script", "program_recorded", name=info["name"])
            return
        if not info["control"]:  # only ur_rtde's control script is emulated; others are recorded
            ctl.log("script", "program_not_emulated", name=info["name"])
            return
        # The realtime interface runs programs only in remote control, powered with brakes released and
        # outside any safety stop; otherwise nothing starts and ur_rtde times out waiting for PLAYING.
        why = None
        if not s["is_in_remote_control"]:
            why = "local control"
        elif s["robot_mode"] != 7:
            why = f"robot mode {ROBOT_MODES.get(s['robot_mode'], s['robot_mode'])}"
        elif s["safety_mode"] not in RUNNABLE_SAFETY:
            why = f"safety mode {SAFETY_MODES.get(s['safety_mode'], s['safety_mode'])}"
        if why is not None:
            ctl.log("script", "program_refused", name=info["name"], reason=why)
            self._record("script_refused", reason=why)
            return
        if self.running:
            self.end("replaced by a new program")
        self.advance(time.monotonic())
        self.running = True
        self.starts += 1
        self.offset, self.realtime = info["offset"], info["realtime"]
        self.executing, self.busy, self.motion, self.teach_mode = False, None, None, False
        self.qd = [0.0] * 6
        # The script's header defaults; servo_target becomes real with the first servoJ.
        self.servo = {"target": None, "speed": 0.0, "acceleration": 0.0, "time": 0.002, "lookahead": 0.1,
                      "gain": 300.0}
        self.end_reason = None
        s["program_state"] = "PLAYING"  # runtime_state PLAYING: what isProgramRunning() waits for
        self._async_progress(-1)  # reset_async_progress()
        self._out_int(0, SCRIPT_READY)  # signal_ready()
        self._record("script_start", offset=self.offset)
        ctl.log("script", "control_script_start", offset=self.offset)

    def end(self, reason: str) -> None:
        """The program ends (stop command, safety stop, dashboard stop, runtime error): the arm stays put."""
        if not self.running:
            return
        self.running = False
        self.executing, self.busy, self.motion, self.teach_mode = False, None, None, False
        self.qd = [0.0] * 6
        s = self.ctl.state
        s["actual_qd"] = [0.0] * 6
        if s["program_state"] in ("PLAYING", "PAUSED"):
            s["program_state"] = "STOPPED"
        self.end_reason = reason
        self._record("script_end", reason=reason)
        self.ctl.log("script", "control_script_end", reason=reason)

    # ---- the main loop -----------------------------------------------------------------------------
    def advance(self, now: float) -> None:
        dt, self.last_t = max(0.0, now - self.last_t), now
        if not self.running:
            return
        state = self.ctl.state["program_state"]
        if state == "STOPPED":  # stopped from outside: dashboard 'stop', 'power off', a side-channel set
            self.end("program stopped")
            return
        if state != "PLAYING":  # paused: nothing runs, nothing moves
            return
        self._move(dt)
        self._step()

    def on_input(self, values: dict, now: float) -> None:
        """An RTDE input package was applied: the script sees it in its next cycle."""
        self.advance(now)
        key = f"input_int_register_{self.offset}"
        if (self.running and values.get(key) == CMD_SERVOJ and self.busy is None
                and self.ctl.state["program_state"] == "PLAYING"):
            # Logged per package, not per cycle: one entry per servoJ() call of the client.
            self.ctl.counters["servoj"] += 1
            self._record("servoj", q=list(self.servo["target"]))

    def _step(self) -> None:
        """One pass of the script's 'while keep_running' body (the busy part is _move's)."""
        if self.busy is not None:
            return
        cmd = self._in_int(0)
        if cmd in self.realtime:
            self._process(cmd)
            if self.running:
                self._out_int(0, SCRIPT_READY)
        elif cmd == CMD_NONE:
            self.executing = False
            self._out_int(0, SCRIPT_READY)
        elif not self.executing:
            self.executing = True
            self._process(cmd)
            if self.running and self.busy is None and cmd != CMD_STOP_SCRIPT:
                self._out_int(0, SCRIPT_DONE)

    def _process(self, cmd: int) -> None:
        s = self.ctl.state
        self.last_cmd = cmd
        if cmd == CMD_SERVOJ:
            self.servo = {"target": [self._in_double(i) for i in range(6)], "speed": self._in_double(6),
                          "acceleration": self._in_double(7), "time": self._in_double(8),
                          "lookahead": self._in_double(9), "gain": self._in_double(10)}
            if not self.teach_mode:
                self.motion = "servo"
        elif cmd in (CMD_SERVO_STOP, CMD_SPEED_STOP, CMD_STOPL, CMD_STOPJ):
            decel = self._in_double(0)
            asynchronous = cmd in (CMD_STOPL, CMD_STOPJ) and self._in_int(1) == 1
            self._record(CMD_NAMES[cmd], a=decel)
            self.stop_decel = decel if decel > 0 else 10.0
            self.motion = "stop" if any(self.qd) else None
            if self.motion == "stop" and not asynchronous:  # stopl() blocks the loop until standstill
                self.busy, self.busy_signals_done = "stop", True
        elif cmd == CMD_MOVEJ:
            q = [self._in_double(i) for i in range(6)]
            speed, asynchronous = self._in_double(6), self._in_int(1) == 1
            self._record("movej", q=q, v=speed, a=self._in_double(7), asynchronous=asynchronous)
            self.move_target, self.move_speed = q, max(speed, 1e-3)
            self.motion = "move"
            if not asynchronous:
                self.busy, self.busy_signals_done = "move", True
        elif cmd == CMD_TEACH_MODE:
            self._record("teach_mode")
            self.teach_mode, self.motion, self.qd = True, None, [0.0] * 6
            s["actual_qd"] = [0.0] * 6
        elif cmd == CMD_END_TEACH_MODE:
            self._record("end_teach_mode")
            self.teach_mode = False
        elif cmd == CMD_PROTECTIVE_STOP:
            self._record("protective_stop")
            self.ctl.protective_stop_at = time.monotonic()
            s["safety_mode"] = 3
            self.end("protective stop")
        elif cmd == CMD_STOP_SCRIPT:
            self._record("stop_script")
            self.end("stop_script")
        else:
            # Not emulated: end the program the way a URScript runtime error does, so a test that strays
            # off the emulated commands fails visibly (ur_rtde returns False) instead of silently passing.
            self._record("unsupported", id=cmd)
            self.end(f"command {cmd} is not emulated by the fake")

    # ---- motion ------------------------------------------------------------------------------------
    def _move(self, dt: float) -> None:
        if self.teach_mode or self.motion is None or dt <= 0:
            return
        s = self.ctl.state
        q = list(s["actual_q"])
        if self.motion == "servo" and self.servo["target"] is not None:
            # servoj as a first-order lag with the lookahead time as time constant, within joint speeds.
            tau = max(self.servo["lookahead"], 0.002)
            alpha = 1.0 - math.exp(-dt / tau)
            for i, target in enumerate(self.servo["target"]):
                step = (target - q[i]) * alpha
                lim = MAX_JOINT_SPEED[i] * dt
                step = max(-lim, min(lim, step))
                q[i] += step
                if abs(target - q[i]) < 1e-7:
                    q[i] = target
                self.qd[i] = step / dt
        elif self.motion == "stop":
            # Decelerate the current joint velocity at the requested rate (rad/s^2 applied to the fastest
            # joint, the others scaled with it so the path keeps its direction).
            v = max(abs(x) for x in self.qd)
            a = self.stop_decel
            if v <= a * dt:
                t_stop = v / a
                q = [qi + qdi * t_stop / 2 for qi, qdi in zip(q, self.qd)]
                self.qd = [0.0] * 6
                self.motion = None
            else:
                scale = (v - a * dt) / v
                q = [qi + qdi * (1 + scale) / 2 * dt for qi, qdi in zip(q, self.qd)]
                self.qd = [x * scale for x in self.qd]
        elif self.motion == "move" and self.move_target is not None:
            # movej at constant speed of the leading joint, all joints arriving together.
            delta = [t - qi for t, qi in zip(self.move_target, q)]
            dist = max(abs(x) for x in delta)
            step = self.move_speed * dt
            if dist <= step:
                q, self.qd, self.motion = list(self.move_target), [0.0] * 6, None
            else:
                self.qd = [x / dist * self.move_speed for x in delta]
                q = [qi + x / dist * step for qi, x in zip(q, delta)]
        s["actual_q"] = q
        s["actual_qd"] = list(self.qd)
        if self.motion is None and self.busy is not None:  # stopl/movej returned: process_cmd ends
            self.busy = None
            if self.busy_signals_done:
                self._out_int(0, SCRIPT_DONE)

    def snapshot(self) -> dict:
        return {
            "control_script_running": self.running,
            "teach_mode": self.teach_mode,
            "servoing": self.motion == "servo",
            "servo_target": self.servo["target"],
            "servo_lookahead": self.servo["lookahead"],
            "servo_gain": self.servo["gain"],
            "servo_time": self.servo["time"],
            "servo_speed": self.servo["speed"],
            "servo_acceleration": self.servo["acceleration"],
            "servo_log": list(self.log),
            "servoj_count": self.ctl.counters.get("servoj", 0),
            "control_script": {"running": self.running, "starts": self.starts, "register_offset": self.offset,
                               "executing": self.executing, "busy": self.busy, "motion": self.motion,
                               "last_cmd": self.last_cmd, "end_reason": self.end_reason},
        }


class Controller:
    """Shared robot state and the protocol logic of the three servers; one lock serializes it."""

    def __init__(self, host: str, initial: dict, verbose: bool = False):
        self.host = host
        self.verbose = verbose
        self.lock = threading.RLock()
        self.t0 = time.monotonic()
        self.state = dict(META_DEFAULTS)
        self.state.update(_rtde_defaults())
        self.gripper = Gripper()
        self.pending = []  # (due monotonic, key, value): delayed mode transitions
        self.protective_stop_at = None
        self.modes = dict(DEFAULT_MODES)
        self.scripts = collections.deque(maxlen=4)  # URScript text clients sent to port 30003
        self.listeners = {}
        self.sessions = {name: set() for name in SERVERS}
        self.rtde_sessions = []
        self.input_owner = {}  # input field -> RtdeSession holding it (the IN_USE rule)
        self.events = collections.deque(maxlen=5000)
        self.dashboard_log = collections.deque(maxlen=5000)
        self.gripper_log = collections.deque(maxlen=5000)
        self.counters = collections.Counter()
        self.stop_event = threading.Event()
        self._fk_cache = (None, None)
        self.script = ControlScript(self)  # before set_state: it advances the script
        self.set_state(initial)

    # ---- bookkeeping -----------------------------------------------------------------------------
    def now(self) -> float:
        return time.monotonic() - self.t0

    def log(self, server: str, event: str, **data) -> None:
        entry = {"t": round(self.now(), 4), "server": server, "event": event, **data}
        with self.lock:
            self.events.append(entry)
        if self.verbose:
            print(json.dumps(entry), file=sys.stderr, flush=True)

    def _apply_pending(self) -> None:
        now = time.monotonic()
        due = [p for p in self.pending if p[0] <= now]
        if due:
            self.pending = [p for p in self.pending if p[0] > now]
            for _, key, value in sorted(due, key=lambda p: p[0]):
                self.state[key] = value

    # ---- state access ----------------------------------------------------------------------------
    def set_state(self, updates: dict) -> None:
        with self.lock:
            self.script.advance(time.monotonic())  # motion up to now happened under the old state
            for key, value in updates.items():
                if key == "gripper":
                    self._set_gripper(value)
                    continue
                if key == "modes":
                    for server, mode in value.items():
                        self.set_mode(server, mode)
                    continue
                if key not in self.state:
                    raise StateError(f"unknown state key: {key!r}")
                typ = OUTPUT_TYPES.get(key) or INPUT_TYPES.get(key)
                if value is not None and typ in TYPE_LENGTHS:
                    if not isinstance(value, (list, tuple)) or len(value) != TYPE_LENGTHS[typ]:
                        raise StateError(f"{key} needs {TYPE_LENGTHS[typ]} numbers, got {value!r}")
                    value = list(value)
                if value is None and key not in DERIVED and key not in ("loaded_program", "known_programs"):
                    raise StateError(f"{key} cannot be null (only derived values can: {DERIVED})")
                if key == "safety_mode" and value == 3 and self.state["safety_mode"] != 3:
                    self.protective_stop_at = time.monotonic()
                # A safety stop or losing power ends a program sent to port 30003 (runtime_state leaves
                # PLAYING; ur_rtde has to re-upload its script), unlike a loaded program, paused below.
                if key == "safety_mode" and value not in RUNNABLE_SAFETY:
                    self.script.end(f"safety mode {SAFETY_MODES.get(value, value)}")
                if key == "robot_mode" and value != 7:
                    self.script.end(f"robot mode {ROBOT_MODES.get(value, value)}")
                if key == "safety_mode" and self.state["program_state"] in ("PLAYING", "PAUSED"):
                    # A protective/safeguard stop pauses the running program; an emergency stop stops it.
                    if value in EMERGENCY_STOPS:
                        self.state["program_state"] = "STOPPED"
                    elif value in (3, 5, 12, 13) and self.state["program_state"] == "PLAYING":
                        self.state["program_state"] = "PAUSED"
                self.state[key] = value
            self.script.advance(time.monotonic())  # a change (program_state STOPPED...) acts at once
            self.log("control", "set", keys=sorted(updates))

    def _set_gripper(self, value: dict) -> None:
        g = self.gripper
        g.advance(time.monotonic(), self._gripper_frozen())
        for key, v in value.items():
            if key in g.config:
                g.config[key] = v
            elif key in g.REGISTERS:
                g.regs[key] = int(v)
            else:
                raise StateError(f"unknown gripper key: {key!r}")

    def _gripper_frozen(self) -> bool:
        return self.state["safety_mode"] in EMERGENCY_STOPS

    def value(self, name: str):
        """Current value of an RTDE output (the lock is held by the caller)."""
        v = self.state[name]
        if v is not None:
            return v
        s = self.state
        if name == "timestamp":  # controller time, advancing in 2 ms control cycles
            return round(self.now() / 0.002) * 0.002
        if name == "target_q":
            return s["actual_q"]
        if name == "actual_TCP_pose":
            key = (tuple(s["actual_q"]), s["robot_model"], tuple(s["tcp_offset"]))
            if self._fk_cache[0] != key:
                self._fk_cache = (key, forward_kinematics(s["actual_q"], s["robot_model"], s["tcp_offset"]))
            return self._fk_cache[1]
        if name == "target_TCP_pose":
            return self.value("actual_TCP_pose")
        if name == "robot_status_bits":
            mode = s["robot_mode"]
            bits = 1 if mode in (4, 5, 6, 7) else 0  # bit 0: power on
            bits |= 2 if s["program_state"] == "PLAYING" else 0  # bit 1: program running
            return bits
        if name == "safety_status":
            return s["safety_mode"]
        if name == "safety_status_bits":
            mode = s["safety_mode"]
            bit_of_mode = {1: 0, 2: 1, 3: 2, 4: 3, 5: 4, 6: 5, 7: 6, 8: 8, 9: 9}
            bits = 1 << bit_of_mode[mode] if mode in bit_of_mode else 0
            if mode in EMERGENCY_STOPS:
                bits |= 1 << 7  # is emergency stopped
            if mode in (3, 5, 6, 7, 12, 13):
                bits |= 1 << 10  # stopped due to safety
            if mode == 12:
                bits |= 1 << 4  # automatic-mode safeguard stop is a safeguard stop
            return bits
        if name == "runtime_state":
            return RUNTIME_STATES[s["program_state"]]
        if name == "speed_scaling":  # no trajectory limiting in the fake: scaling is the slider
            return s["target_speed_fraction"]
        raise KeyError(name)

    def snapshot(self) -> dict:
        with self.lock:
            self._apply_pending()
            self.script.advance(time.monotonic())
            self.gripper.advance(time.monotonic(), self._gripper_frozen())
            out = {}
            for key in self.state:
                out[key] = self.value(key) if key in OUTPUT_TYPES else self.state[key]
            bits = out["actual_digital_output_bits"]
            out["standard_digital_outputs"] = [bool(bits >> i & 1) for i in range(8)]
            out["configurable_digital_outputs"] = [bool(bits >> (8 + i) & 1) for i in range(8)]
            out["tool_digital_outputs"] = [bool(bits >> 16 & 1), bool(bits >> 17 & 1)]
            out["gripper"] = self.gripper.snapshot()
            out["modes"] = dict(self.modes)
            out["rtde_sessions"] = [sess.describe() for sess in self.rtde_sessions]
            out["events"] = list(self.events)
            out["dashboard_log"] = list(self.dashboard_log)
            out["gripper_log"] = list(self.gripper_log)
            out["scripts"] = list(self.scripts)
            out["counters"] = dict(self.counters)
            out.update(self.script.snapshot())
            out["uptime_s"] = round(self.now(), 4)
            return out

    def clear_logs(self) -> None:
        with self.lock:
            self.events.clear()
            self.dashboard_log.clear()
            self.gripper_log.clear()
            self.scripts.clear()
            self.counters.clear()
            self.script.log.clear()

    def set_mode(self, server: str, mode: str) -> None:
        if server not in SERVERS or mode not in SERVER_MODES:
            raise StateError(f"server must be one of {SERVERS} and mode one of {SERVER_MODES}")
        with self.lock:
            self.modes[server] = mode
            listener = self.listeners.get(server)
        if listener is not None:
            listener.stop() if mode == "off" else listener.start()
        self.log("control", "mode", target=server, mode=mode)

    def drop(self, server: str) -> int:
        with self.lock:
            conns = list(self.sessions[server])
        for conn in conns:
            _hard_close(conn)
        self.log("control", "drop", target=server, count=len(conns))
        return len(conns)

    # ---- RTDE ------------------------------------------------------------------------------------
    def version_tuple(self) -> tuple[int, int, int, int]:
        parts = [int(p) for p in str(self.state["software_version"]).split(".")[:4]]
        return tuple((parts + [0, 0, 0, 0])[:4])

    def output_type(self, name: str) -> str:
        typ = OUTPUT_TYPES.get(name)
        if typ is None:
            return "NOT_FOUND"
        need = OUTPUT_MIN_VERSION.get(name)
        if need is not None and self.version_tuple()[:2] < need:
            return "NOT_FOUND"
        return typ

    def apply_inputs(self, names: list[str], values: list, session) -> None:
        d = dict(zip(names, values))
        with self.lock:
            s = self.state
            bits = s["actual_digital_output_bits"]
            for mask_name, value_name, shift, width in (
                ("standard_digital_output_mask", "standard_digital_output", 0, 8),
                ("configurable_digital_output_mask", "configurable_digital_output", 8, 8),
                ("tool_digital_output_mask", "tool_digital_output", 16, 2),  # tool outputs: bits 16-17
            ):
                if mask_name in d and value_name in d:
                    mask = d[mask_name] & ((1 << width) - 1)
                    bits = (bits & ~(mask << shift)) | ((d[value_name] & mask) << shift)
            s["actual_digital_output_bits"] = bits
            if d.get("speed_slider_mask") == 1 and "speed_slider_fraction" in d:
                s["target_speed_fraction"] = min(1.0, max(0.0, d["speed_slider_fraction"]))
            if "standard_analog_output_mask" in d:
                mask, types = d["standard_analog_output_mask"], d.get("standard_analog_output_type", 0)
                io_types = s["analog_io_types"]
                for i in (0, 1):
                    if mask >> i & 1 and f"standard_analog_output_{i}" in d:
                        ratio = min(1.0, max(0.0, d[f"standard_analog_output_{i}"]))
                        voltage = bool(types >> i & 1)
                        s[f"standard_analog_output{i}"] = ratio * 10.0 if voltage else 4.0 + 16.0 * ratio
                        io_types = (io_types & ~(1 << (2 + i))) | (int(voltage) << (2 + i))
                s["analog_io_types"] = io_types
            for name, value in d.items():
                if name.startswith("input_") or name == "external_force_torque":
                    s[name] = list(value) if isinstance(value, tuple) else value
            self.counters["rtde_input_packages"] += 1
            self.script.on_input(d, time.monotonic())
        self.log("rtde", "input", session=session.sid, values={k: _jsonable(v) for k, v in d.items()})

    # ---- dashboard -------------------------------------------------------------------------------
    def dashboard(self, line: str) -> tuple[str, bool]:
        """One request line -> (response line, close connection afterwards)."""
        cmd = line.strip()
        with self.lock:
            self._apply_pending()
            self.dashboard_log.append(cmd)
            self.script.advance(time.monotonic())
            if cmd.startswith("load "):  # loading a program stops a script sent to port 30003
                self.script.end(f"dashboard {cmd}")
            response, close = self._dashboard(cmd)
            self.script.advance(time.monotonic())  # 'stop' / 'power off' end the script at once
        self.log("dashboard", "command", command=cmd, response=response)
        return response, close

    def _dashboard(self, cmd: str) -> tuple[str, bool]:
        s, now = self.state, time.monotonic()
        program = s["loaded_program"]
        if cmd == "quit":
            return "Disconnected", True
        if cmd == "shutdown":
            threading.Thread(target=self._shutdown_servers, daemon=True).start()
            return "Shutting down", True
        if cmd.startswith("load installation "):
            return f"Loading installation: {cmd[len('load installation '):].strip()}", False
        if cmd.startswith("load "):
            name = cmd[5:].strip()
            if s["known_programs"] is not None and name not in s["known_programs"]:
                return f"File not found: {name}", False
            s["loaded_program"], s["program_state"] = name, "STOPPED"
            return f"Loading program: {name}", False
        if cmd == "play":
            if program is None or s["robot_mode"] != 7 or s["safety_mode"] not in (1, 2):
                return "Failed to execute: play", False
            s["program_state"] = "PLAYING"
            return "Starting program", False
        if cmd == "stop":
            # A program sent to port 30003 is the controller's current program too: ur_rtde stops a script it
            # finds running with stopScript() and then this, and throws unless the answer is "Stopped".
            if program is None and self.script.starts == 0:
                return "Failed to execute: stop", False
            s["program_state"] = "STOPPED"
            return "Stopped", False
        if cmd == "pause":
            if s["program_state"] != "PLAYING":
                return "Failed to execute: pause", False
            s["program_state"] = "PAUSED"
            return "Pausing program", False
        if cmd == "running":
            return f"Program running: {str(s['program_state'] == 'PLAYING').lower()}", False
        if cmd == "robotmode":
            return f"Robotmode: {ROBOT_MODES.get(s['robot_mode'], str(s['robot_mode']))}", False
        if cmd == "get loaded program":
            return (f"Loaded program: {program}" if program else "No program loaded"), False
        if cmd.startswith("popup"):
            return "showing popup", False
        if cmd == "close popup":
            return "closing popup", False
        if cmd.startswith("addToLog"):
            return ("Added log message" if cmd[len("addToLog"):].strip() else "No log message to add"), False
        if cmd == "isProgramSaved":
            return f"{str(bool(s['program_saved'])).lower()} {_program_name(program)}", False
        if cmd == "programState":
            return f"{s['program_state']} {_program_name(program)}", False
        if cmd == "PolyscopeVersion":
            return f"URSoftware {s['software_version']} ({s['software_build_date']})", False
        if cmd == "version":
            return f"Version information: {s['software_version']}", False
        if cmd.startswith("setUserRole "):
            return f"Setting user role: {cmd[len('setUserRole '):].strip()}", False
        if cmd == "power on":
            if s["robot_mode"] in (3, 0, 1):
                s["robot_mode"] = 4
                self.pending.append((now + s["power_on_delay_s"], "robot_mode", 5))
            return "Powering on", False
        if cmd == "power off":
            s["robot_mode"], s["program_state"] = 3, "STOPPED"
            self.pending = [p for p in self.pending if p[1] != "robot_mode"]
            return "Powering off", False
        if cmd == "brake release":
            if s["robot_mode"] in (4, 5):
                self.pending.append((now + s["brake_release_delay_s"], "robot_mode", 7))
            return "Brake releasing", False
        if cmd == "safetymode":
            return f"Safetymode: {SAFETY_MODES.get(s['safety_mode'], str(s['safety_mode']))}", False
        if cmd == "safetystatus":
            status = self.value("safety_status")
            return f"Safetystatus: {SAFETY_MODES.get(status, str(status))}", False
        if cmd == "unlock protective stop":
            if s["safety_mode"] == 3:
                since = now - (self.protective_stop_at or 0.0)
                if since < s["protective_stop_unlock_delay_s"]:
                    return ("Cannot unlock protective stop until 5s after occurrence. "
                            "Always inspect cause of protective stop before unlocking"), False
                s["safety_mode"] = 1
            return "Protective stop releasing", False
        if cmd == "close safety popup":
            return "closing safety popup", False
        if cmd == "restart safety":
            if s["safety_mode"] in (8, 9, 3, 5):
                s["safety_mode"], s["robot_mode"], s["program_state"] = 1, 3, "STOPPED"
            return "Restarting safety", False
        if cmd == "is in remote control":
            return str(bool(s["is_in_remote_control"])).lower(), False
        if cmd == "get serial number":
            return str(s["serial_number"]), False
        if cmd == "get robot model":
            return str(s["robot_model"]), False
        if cmd == "get operational mode":
            return str(s["operational_mode"]), False
        if cmd.startswith("set operational mode "):
            mode = cmd[len("set operational mode "):].strip()
            s["operational_mode"] = mode.upper()
            return f"Operational mode '{mode}' is set", False
        if cmd == "clear operational mode":
            return ("No longer controlling the operational mode. "
                    f"Current operational mode: '{str(s['operational_mode']).lower()}'."), False
        return f"could not understand: '{cmd}'", False

    def _shutdown_servers(self) -> None:
        time.sleep(0.05)  # let the "Shutting down" reply leave first
        for server in SERVERS:
            if self.modes[server] != "off":
                self.set_mode(server, "off")
            self.drop(server)

    # ---- Robotiq URCap ---------------------------------------------------------------------------
    def gripper_command(self, line: str) -> str:
        """One URCap request line -> reply (no newline after 'ack', a newline after 'VAR value')."""
        text = line.strip()
        tokens = text.split()
        with self.lock:
            now = time.monotonic()
            self.gripper_log.append({"t": round(self.now(), 4), "command": text})
            g = self.gripper
            g.advance(now, self._gripper_frozen())
            if len(tokens) == 2 and tokens[0] == "GET":
                name = tokens[1]
                if name not in g.REGISTERS:
                    return "?\n"
                if self._gripper_frozen():  # tool power off: the URCap answers a question mark
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
                g.advance(now, self._gripper_frozen())
                return "ack"
            return "?"


def _program_name(program) -> str:
    return os.path.basename(program) if program else "<unnamed>"


def _jsonable(v):
    return list(v) if isinstance(v, tuple) else v


def _hard_close(conn: socket.socket) -> None:
    try:
        conn.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    try:
        conn.close()
    except OSError:
        pass


# ---------------------------------------------------------------------------------------------------
# RTDE session
# ---------------------------------------------------------------------------------------------------
class Recipe:
    def __init__(self, rid: int, names: list[str], types: list[str], frequency: float, with_id: bool):
        self.id = rid
        self.names = names
        self.types = types
        self.frequency = frequency
        self.period = 1.0 / frequency if frequency > 0 else None
        fmt = ">" + ("B" if with_id else "") + "".join(TYPE_FORMATS[t] for t in types)
        self.struct = struct.Struct(fmt)
        self.next_due = 0.0


class RtdeSession:
    _ids = iter(range(1, 1 << 30))

    def __init__(self, ctl: Controller, conn: socket.socket, peer):
        self.ctl = ctl
        self.conn = conn
        self.peer = f"{peer[0]}:{peer[1]}"
        self.sid = next(self._ids)
        self.protocol = 1  # until 'V' negotiates 2
        self.outputs: list[Recipe] = []
        self.inputs: dict[int, Recipe] = {}
        self.next_output_id = 1
        self.next_input_id = 1
        self.started = False
        self.send_lock = threading.Lock()
        self.wake = threading.Event()
        self.closed = False
        self.packets_sent = 0

    def describe(self) -> dict:
        return {
            "id": self.sid, "peer": self.peer, "protocol": self.protocol, "started": self.started,
            "outputs": [{"id": r.id, "frequency": r.frequency, "names": r.names} for r in self.outputs],
            "inputs": {str(r.id): r.names for r in self.inputs.values()},
            "packets_sent": self.packets_sent,
        }

    def send(self, cmd: int, payload: bytes = b"") -> None:
        with self.send_lock:
            self.conn.sendall(struct.pack(">HB", len(payload) + 3, cmd) + payload)

    def text_message(self, message: str, level: int = 1) -> None:
        """Controller -> client 'M' (v2: length-prefixed message and source, then the warning level)."""
        msg, src = message.encode()[:255], b"RTDE"
        if self.protocol >= 2:
            self.send(RTDE_TEXT_MESSAGE, bytes([len(msg)]) + msg + bytes([len(src)]) + src + bytes([level]))
        else:
            self.send(RTDE_TEXT_MESSAGE, bytes([level]) + msg)

    def run(self) -> None:
        ctl = self.ctl
        with ctl.lock:
            ctl.rtde_sessions.append(self)
            ctl.counters["rtde_connections"] += 1
        ctl.log("rtde", "connect", session=self.sid, peer=self.peer)
        sender = threading.Thread(target=self._sender, daemon=True, name=f"rtde-send-{self.sid}")
        sender.start()
        buf = b""
        try:
            while True:
                data = self.conn.recv(65536)
                if not data:
                    break
                buf += data
                while len(buf) >= 3:
                    size, cmd = struct.unpack_from(">HB", buf)
                    if size < 3:
                        raise ConnectionError(f"bad RTDE header size {size}")
                    if len(buf) < size:
                        break
                    payload, buf = buf[3:size], buf[size:]
                    self.handle(cmd, payload)
        except (OSError, ConnectionError, struct.error) as exc:
            ctl.log("rtde", "error", session=self.sid, error=str(exc))
        finally:
            self.closed = True
            self.started = False
            self.wake.set()
            with ctl.lock:
                if self in ctl.rtde_sessions:
                    ctl.rtde_sessions.remove(self)
                for name, owner in list(ctl.input_owner.items()):
                    if owner is self:  # inputs are released when their client goes
                        del ctl.input_owner[name]
            _hard_close(self.conn)
            ctl.log("rtde", "disconnect", session=self.sid)

    def handle(self, cmd: int, payload: bytes) -> None:
        ctl = self.ctl
        if cmd == RTDE_REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            accepted = version in (1, 2)
            if accepted:
                self.protocol = version
            ctl.log("rtde", "protocol_version", session=self.sid, requested=version, accepted=accepted)
            self.send(cmd, bytes([int(accepted)]))
        elif cmd == RTDE_GET_URCONTROL_VERSION:
            with ctl.lock:
                version = ctl.version_tuple()
            self.send(cmd, struct.pack(">IIII", *version))
        elif cmd == RTDE_TEXT_MESSAGE:
            ctl.log("rtde", "text_message", session=self.sid, payload=payload.decode("latin-1"))
        elif cmd == RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS:
            self.setup_outputs(payload)
        elif cmd == RTDE_CONTROL_PACKAGE_SETUP_INPUTS:
            self.setup_inputs(payload)
        elif cmd == RTDE_CONTROL_PACKAGE_START:
            accepted = bool(self.outputs) or bool(self.inputs)
            self.started = accepted
            for r in self.outputs:
                r.next_due = time.monotonic()
            ctl.log("rtde", "start", session=self.sid, accepted=accepted)
            self.send(cmd, bytes([int(accepted)]))
            self.wake.set()
        elif cmd == RTDE_CONTROL_PACKAGE_PAUSE:
            self.started = False
            ctl.log("rtde", "pause", session=self.sid)
            self.send(cmd, bytes([1]))
        elif cmd == RTDE_DATA_PACKAGE:
            self.input_package(payload)
        else:
            ctl.log("rtde", "unknown_command", session=self.sid, command=cmd)
            self.text_message(f"Unknown command {cmd}", level=2)

    def setup_outputs(self, payload: bytes) -> None:
        ctl = self.ctl
        if self.protocol >= 2:
            (frequency,) = struct.unpack(">d", payload[:8])
            names_str = payload[8:].decode("latin-1")
        else:
            frequency, names_str = RTDE_V1_FREQUENCY, payload.decode("latin-1")
        # ur_rtde ends its list with a comma; empty names are not fields.
        names = [n.strip() for n in names_str.split(",") if n.strip()]
        with ctl.lock:
            types = [ctl.output_type(n) for n in names]
            max_freq = float(ctl.state["max_rtde_frequency"])
        ok = bool(names) and "NOT_FOUND" not in types and 0 < frequency <= max_freq and not self.started
        rid = 0
        if ok:
            if self.protocol < 2:  # protocol 1 has a single output recipe
                self.outputs.clear()
            rid = self.next_output_id
            self.next_output_id += 1
            self.outputs.append(Recipe(rid, names, types, frequency, with_id=self.protocol >= 2))
        ctl.log("rtde", "output_setup", session=self.sid, recipe=rid, frequency=frequency, names=names,
                types=types, ok=ok)
        reply = ",".join(types).encode()
        self.send(RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS, (bytes([rid]) + reply) if self.protocol >= 2 else reply)

    def setup_inputs(self, payload: bytes) -> None:
        ctl = self.ctl
        names = [n.strip() for n in payload.decode("latin-1").split(",") if n.strip()]
        with ctl.lock:
            fieldbus = set(ctl.state["fieldbus_inputs"])
            types = []
            for n in names:
                owner = ctl.input_owner.get(n)
                if n not in INPUT_TYPES:
                    types.append("NOT_FOUND")
                elif n in fieldbus or (owner is not None and owner is not self):
                    types.append("IN_USE")
                else:
                    types.append(INPUT_TYPES[n])
            ok = bool(names) and not any(t in ("NOT_FOUND", "IN_USE") for t in types) and not self.started
            rid = 0
            if ok:
                rid = self.next_input_id
                self.next_input_id += 1
                self.inputs[rid] = Recipe(rid, names, types, 0.0, with_id=self.protocol >= 2)
                for n in names:
                    ctl.input_owner[n] = self
        ctl.log("rtde", "input_setup", session=self.sid, recipe=rid, names=names, types=types, ok=ok)
        self.send(RTDE_CONTROL_PACKAGE_SETUP_INPUTS, bytes([rid]) + ",".join(types).encode())

    def input_package(self, payload: bytes) -> None:
        ctl = self.ctl
        if self.protocol >= 2:
            rid = payload[0] if payload else 0
        else:
            rid = min(self.inputs) if self.inputs else 0
        recipe = self.inputs.get(rid)
        if recipe is None or len(payload) != recipe.struct.size:
            ctl.log("rtde", "bad_input_package", session=self.sid, recipe=rid, size=len(payload))
            with ctl.lock:
                ctl.counters["rtde_bad_input_packages"] += 1
            return
        flat = list(recipe.struct.unpack(payload))
        if self.protocol >= 2:
            flat = flat[1:]
        values = []
        for t in recipe.types:
            n = TYPE_LENGTHS.get(t)
            if n:
                values.append(tuple(flat[:n]))
                flat = flat[n:]
            else:
                values.append(flat.pop(0))
        ctl.apply_inputs(recipe.names, values, self)

    def _pack(self, recipe: Recipe) -> bytes:
        ctl = self.ctl
        flat = [recipe.id] if self.protocol >= 2 else []
        with ctl.lock:
            ctl._apply_pending()
            ctl.script.advance(time.monotonic())  # the control script's cycle and the arm's motion
            for name, t in zip(recipe.names, recipe.types):
                v = ctl.value(name)
                if t in TYPE_LENGTHS:
                    flat.extend(float(x) if t.endswith("D") else int(x) for x in v)
                elif t == "DOUBLE":
                    flat.append(float(v))
                elif t == "BOOL":
                    flat.append(bool(v))
                else:
                    flat.append(int(v))
        return recipe.struct.pack(*flat)

    def _sender(self) -> None:
        """Data packages at each output recipe's frequency; late cycles are skipped, as the controller does."""
        while not self.closed:
            if not self.started or not self.outputs:
                self.wake.wait(0.05)
                self.wake.clear()
                continue
            now = time.monotonic()
            for recipe in list(self.outputs):
                if now >= recipe.next_due:
                    try:
                        self.send(RTDE_DATA_PACKAGE, self._pack(recipe))
                    except OSError:
                        self.closed = True
                        return
                    self.packets_sent += 1
                    recipe.next_due += recipe.period
                    if recipe.next_due < now:
                        recipe.next_due = now + recipe.period
            nxt = min((r.next_due for r in self.outputs), default=now + 0.05)
            delay = nxt - time.monotonic()
            if delay > 0:
                time.sleep(delay)


# ---------------------------------------------------------------------------------------------------
# Servers
# ---------------------------------------------------------------------------------------------------
class Listener:
    def __init__(self, ctl: Controller, name: str, host: str, port: int, handler):
        self.ctl, self.name, self.host, self.port, self.handler = ctl, name, host, port, handler
        self.sock = None
        self.thread = None
        self.lock = threading.Lock()

    def start(self) -> None:
        with self.lock:
            if self.sock is not None:
                return
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            # Restarts on the same address must not wait out TIME_WAIT of the previous fake.
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((self.host, self.port))
            sock.listen(16)
            sock.settimeout(0.2)  # lets stop() end the accept loop without relying on close() waking it
            self.sock = sock
            self.thread = threading.Thread(target=self._accept_loop, args=(sock,), daemon=True,
                                           name=f"accept-{self.name}")
            self.thread.start()

    def stop(self) -> None:
        """Stops listening; once this returns, new connections are refused (ECONNREFUSED)."""
        with self.lock:
            sock, self.sock, thread = self.sock, None, self.thread
        if sock is None:
            return
        try:
            # On Linux this stops the listener at once (pending and new connects are refused), even
            # while the accept thread still sits in poll() on the descriptor.
            sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        if thread is not None:
            thread.join(1.0)  # the fd really closes only when no thread is inside a call on it
        sock.close()

    def _accept_loop(self, sock: socket.socket) -> None:
        while self.sock is sock:
            try:
                conn, peer = sock.accept()
            except socket.timeout:
                continue
            except OSError:
                break
            conn.settimeout(None)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            mode = self.ctl.modes.get(self.name, "serve")
            if mode == "refuse":
                self.ctl.log(self.name, "refused", peer=f"{peer[0]}:{peer[1]}")
                _hard_close(conn)
                continue
            threading.Thread(target=self._serve, args=(conn, peer, mode), daemon=True,
                             name=f"{self.name}-{peer[1]}").start()

    def _serve(self, conn: socket.socket, peer, mode: str) -> None:
        sessions = self.ctl.sessions.setdefault(self.name, set())
        with self.ctl.lock:
            sessions.add(conn)
        try:
            if mode == "silent":
                self.ctl.log(self.name, "silent_connect", peer=f"{peer[0]}:{peer[1]}")
                while conn.recv(65536):
                    pass
            else:
                self.handler(conn, peer)
        except OSError:
            pass
        finally:
            with self.ctl.lock:
                sessions.discard(conn)
            _hard_close(conn)


def _lines(conn: socket.socket):
    """Yields request lines (without the line end) until EOF."""
    buf = b""
    while True:
        data = conn.recv(4096)
        if not data:
            return
        buf += data
        while b"\n" in buf:
            line, buf = buf.split(b"\n", 1)
            yield line.rstrip(b"\r").decode("utf-8", "replace")


def serve_dashboard(ctl: Controller, conn: socket.socket, peer) -> None:
    ctl.log("dashboard", "connect", peer=f"{peer[0]}:{peer[1]}")
    conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
    for line in _lines(conn):
        response, close = ctl.dashboard(line)
        conn.sendall(response.encode() + b"\n")
        if close:
            break
    ctl.log("dashboard", "disconnect", peer=f"{peer[0]}:{peer[1]}")


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
                replies.append(ctl.gripper_command(line.decode("utf-8", "replace")))
        if replies:
            conn.sendall("".join(replies).encode())
    ctl.log("gripper", "disconnect", peer=f"{peer[0]}:{peer[1]}")


def serve_script(ctl: Controller, conn: socket.socket, peer) -> None:
    """The realtime interface: records the URScript clients send and hands each complete program over.

    ur_rtde keeps this connection open and sends a program whenever it (re)starts its control script, so a
    program is complete at its closing top-level ``end`` line, not at EOF. A bare line outside ``def``/``sec``
    is a one-line program, as on the controller.
    """
    ctl.log("script", "connect", peer=f"{peer[0]}:{peer[1]}")
    chunks = bytearray()
    with ctl.lock:
        ctl.scripts.append("")
        index = len(ctl.scripts) - 1
    pending = b""  # bytes after the last complete line
    program: list[str] = []  # lines of the program being received
    while True:
        data = conn.recv(65536)
        if not data:
            break
        chunks += data
        with ctl.lock:
            if index < len(ctl.scripts):
                ctl.scripts[index] = chunks.decode("utf-8", "replace")
        pending += data
        *lines, pending = pending.split(b"\n")
        for raw in lines:
            line = raw.decode("utf-8", "replace").rstrip("\r")
            if not program:
                if re.match(r"(def|sec)\s+\w+\s*\(", line):
                    program = [line]
                elif line.strip():
                    with ctl.lock:
                        ctl.script.program_received(line + "\n")
                continue
            program.append(line)
            if line.rstrip() == "end":  # top level: inner blocks' 'end' are indented
                text, program = "\n".join(program) + "\n", []
                ctl.log("script", "program", chars=len(text))
                with ctl.lock:
                    ctl.script.program_received(text)
    ctl.log("script", "disconnect", peer=f"{peer[0]}:{peer[1]}", received=len(chunks))


def serve_control(ctl: Controller, conn: socket.socket, peer) -> None:
    """Side channel: 'get', 'set {json}', 'mode {json}', 'drop {json}', 'clear', 'ping', 'quit'."""
    for line in _lines(conn):
        line = line.strip()
        if not line:
            continue
        verb, _, rest = line.partition(" ")
        try:
            arg = json.loads(rest) if rest.strip() else {}
            if verb == "get":
                reply = {"ok": True, "state": ctl.snapshot()}
            elif verb == "set":
                ctl.set_state(arg)
                reply = {"ok": True}
            elif verb == "mode":
                for server, mode in arg.items():
                    ctl.set_mode(server, mode)
                reply = {"ok": True, "modes": dict(ctl.modes)}
            elif verb == "drop":
                servers = arg.get("servers", list(SERVERS)) if isinstance(arg, dict) else arg
                reply = {"ok": True, "dropped": {s: ctl.drop(s) for s in servers}}
            elif verb == "clear":
                ctl.clear_logs()
                reply = {"ok": True}
            elif verb == "ping":
                reply = {"ok": True, "pid": os.getpid()}
            elif verb == "quit":
                conn.sendall(b'{"ok": true}\n')
                ctl.stop_event.set()
                return
            else:
                reply = {"ok": False, "error": f"unknown command {verb!r}"}
        except (StateError, ValueError, KeyError, TypeError, AttributeError) as exc:
            reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        conn.sendall(json.dumps(reply, default=_jsonable).encode() + b"\n")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--host", required=True, help="loopback address to serve on, e.g. 127.0.0.7")
    p.add_argument("--control-port", type=int, default=CONTROL_PORT)
    p.add_argument("--rtde-port", type=int, default=RTDE_PORT)
    p.add_argument("--dashboard-port", type=int, default=DASHBOARD_PORT)
    p.add_argument("--gripper-port", type=int, default=GRIPPER_PORT)
    p.add_argument("--script-port", type=int, default=SCRIPT_PORT)
    for server in SERVERS:
        p.add_argument(f"--no-{server}", action="store_true", help=f"do not listen on the {server} port")
    p.add_argument("--mode", action="append", default=[], metavar="SERVER=MODE",
                   help=f"start a server in a mode: {', '.join(SERVER_MODES)}")
    p.add_argument("--state", default="{}", help="initial state as JSON (keys as the side channel's 'set')")
    p.add_argument("--exit-with-parent", action="store_true", help="exit when the parent process goes away")
    p.add_argument("--verbose", action="store_true", help="print every event to stderr")
    args = p.parse_args(argv)

    ctl = Controller(args.host, json.loads(args.state), verbose=args.verbose)
    for item in args.mode:
        server, _, mode = item.partition("=")
        if server not in SERVERS or mode not in SERVER_MODES:
            p.error(f"--mode {item!r}: SERVER in {SERVERS}, MODE in {SERVER_MODES}")
        ctl.modes[server] = mode
    for server in SERVERS:
        if getattr(args, f"no_{server}"):
            ctl.modes[server] = "off"

    handlers = {
        "rtde": (args.rtde_port, lambda conn, peer: RtdeSession(ctl, conn, peer).run()),
        "dashboard": (args.dashboard_port, lambda conn, peer: serve_dashboard(ctl, conn, peer)),
        "gripper": (args.gripper_port, lambda conn, peer: serve_gripper(ctl, conn, peer)),
        "script": (args.script_port, lambda conn, peer: serve_script(ctl, conn, peer)),
    }
    control = Listener(ctl, "control", args.host, args.control_port, lambda c, a: serve_control(ctl, c, a))
    try:
        control.start()
        for server, (port, handler) in handlers.items():
            ctl.listeners[server] = Listener(ctl, server, args.host, port, handler)
            if ctl.modes[server] != "off":
                ctl.listeners[server].start()
    except OSError as exc:
        print(f"FAILED bind on {args.host}: {exc}", flush=True)
        return 2

    signal.signal(signal.SIGTERM, lambda *_: ctl.stop_event.set())
    ports = {"control": args.control_port, **{s: handlers[s][0] for s in SERVERS}}
    print("READY " + json.dumps({"host": args.host, "pid": os.getpid(), "ports": ports,
                                 "modes": ctl.modes}), flush=True)
    parent = os.getppid()
    while not ctl.stop_event.wait(0.25):
        if args.exit_with_parent and os.getppid() != parent:
            break
    return 0


if __name__ == "__main__":
    sys.exit(main())
