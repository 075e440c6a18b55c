"""RTDE (port 30004): the binary protocol, versions 1 and 2, its recipes, and the output and input fields of
the RTDE guide with what an input package does to the robot."""

from __future__ import annotations

import socket
import struct
import threading
import time
from typing import TYPE_CHECKING

from .servers import hard_close, jsonable

if TYPE_CHECKING:
    from .state import Controller

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
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
TYPE_LENGTHS = {"VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}


def _output_types() -> dict[str, str]:
    """Output fields of the RTDE guide (e-Series 5.x), name -> type."""
    v6, v3, d = "VECTOR6D", "VECTOR3D", "DOUBLE"
    t = {
        "timestamp": d,
        "target_q": v6,
        "target_qd": v6,
        "target_qdd": v6,
        "target_current": v6,
        "target_moment": v6,
        "actual_q": v6,
        "actual_qd": v6,
        "actual_current": v6,
        "actual_current_window": v6,
        "joint_control_output": v6,
        "actual_TCP_pose": v6,
        "actual_TCP_speed": v6,
        "actual_TCP_force": v6,
        "target_TCP_pose": v6,
        "target_TCP_speed": v6,
        "actual_digital_input_bits": "UINT64",
        "joint_temperatures": v6,
        "actual_execution_time": d,
        "robot_mode": "INT32",
        "joint_mode": "VECTOR6INT32",
        "safety_mode": "INT32",
        "safety_status": "INT32",
        "actual_tool_accelerometer": v3,
        "speed_scaling": d,
        "target_speed_fraction": d,
        "actual_momentum": d,
        "actual_main_voltage": d,
        "actual_robot_voltage": d,
        "actual_robot_current": d,
        "actual_joint_voltage": v6,
        "actual_digital_output_bits": "UINT64",
        "runtime_state": "UINT32",
        "elbow_position": v3,
        "elbow_velocity": v3,
        "robot_status_bits": "UINT32",
        "safety_status_bits": "UINT32",
        "analog_io_types": "UINT32",
        "standard_analog_input0": d,
        "standard_analog_input1": d,
        "standard_analog_output0": d,
        "standard_analog_output1": d,
        "io_current": d,
        "euromap67_input_bits": "UINT32",
        "euromap67_output_bits": "UINT32",
        "euromap67_24V_voltage": d,
        "euromap67_24V_current": d,
        "tool_mode": "UINT32",
        "tool_analog_input_types": "UINT32",
        "tool_analog_input0": d,
        "tool_analog_input1": d,
        "tool_output_voltage": "INT32",
        "tool_output_current": d,
        "tool_temperature": d,
        "tcp_force_scalar": d,
        "output_bit_registers0_to_31": "UINT32",
        "output_bit_registers32_to_63": "UINT32",
        "input_bit_registers0_to_31": "UINT32",
        "input_bit_registers32_to_63": "UINT32",
        "tool_output_mode": "UINT8",
        "tool_digital_output0_mode": "UINT8",
        "tool_digital_output1_mode": "UINT8",
        "payload": d,
        "payload_cog": v3,
        "payload_inertia": v6,
        "script_control_line": "UINT32",
        "ft_raw_wrench": v6,
        "joint_position_deviation_ratio": d,
        "collision_detection_ratio": d,
        "time_scale_source": "UINT32",
        "actual_current_as_torque": v6,
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
        "speed_slider_mask": "UINT32",
        "speed_slider_fraction": "DOUBLE",
        "standard_digital_output_mask": "UINT8",
        "standard_digital_output": "UINT8",
        "configurable_digital_output_mask": "UINT8",
        "configurable_digital_output": "UINT8",
        "tool_digital_output_mask": "UINT8",
        "tool_digital_output": "UINT8",
        "standard_analog_output_mask": "UINT8",
        "standard_analog_output_type": "UINT8",
        "standard_analog_output_0": "DOUBLE",
        "standard_analog_output_1": "DOUBLE",
        "input_bit_registers0_to_31": "UINT32",
        "input_bit_registers32_to_63": "UINT32",
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


def version_tuple(ctl: Controller) -> tuple[int, int, int, int]:
    parts = [int(p) for p in str(ctl.state["software_version"]).split(".")[:4]]
    return tuple((parts + [0, 0, 0, 0])[:4])


def output_type(ctl: Controller, name: str) -> str:
    typ = OUTPUT_TYPES.get(name)
    if typ is None:
        return "NOT_FOUND"
    need = OUTPUT_MIN_VERSION.get(name)
    if need is not None and version_tuple(ctl)[:2] < need:
        return "NOT_FOUND"
    return typ


def apply_inputs(ctl: Controller, names: list[str], values: list, session) -> None:
    d = dict(zip(names, values))
    with ctl.lock:
        s = ctl.state
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
        ctl.counters["rtde_input_packages"] += 1
        ctl.script.on_input(d, time.monotonic())
    ctl.log("rtde", "input", session=session.sid, values={k: jsonable(v) for k, v in d.items()})


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
            "id": self.sid,
            "peer": self.peer,
            "protocol": self.protocol,
            "started": self.started,
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
            hard_close(self.conn)
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
                version = version_tuple(ctl)
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
            types = [output_type(ctl, n) for n in names]
            max_freq = float(ctl.state["max_rtde_frequency"])
        ok = bool(names) and "NOT_FOUND" not in types and 0 < frequency <= max_freq and not self.started
        rid = 0
        if ok:
            if self.protocol < 2:  # protocol 1 has a single output recipe
                self.outputs.clear()
            rid = self.next_output_id
            self.next_output_id += 1
            self.outputs.append(Recipe(rid, names, types, frequency, with_id=self.protocol >= 2))
        ctl.log(
            "rtde",
            "output_setup",
            session=self.sid,
            recipe=rid,
            frequency=frequency,
            names=names,
            types=types,
            ok=ok,
        )
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
        if self.protocol >= 2:  # noqa: SIM108  (a nested ternary reads worse)
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
        apply_inputs(ctl, recipe.names, values, self)

    def _pack(self, recipe: Recipe) -> bytes:
        ctl = self.ctl
        flat = [recipe.id] if self.protocol >= 2 else []
        with ctl.lock:
            ctl.apply_pending()
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
        """Data packages at each output recipe's frequency; late cycles are skipped, as on the controller."""
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
