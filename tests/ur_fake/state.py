"""The controller's shared state: the robot values every protocol reads and writes, one lock over them and
the protocol handlers, and the logs of what the clients did."""

from __future__ import annotations

import collections
import json
import sys
import threading
import time

from .arm import EMERGENCY_STOPS, ROBOT_MODES, RUNTIME_STATES, SAFETY_MODES, forward_kinematics
from .gripper import Gripper
from .rtde import INPUT_TYPES, OUTPUT_TYPES, RTDE_MAX_FREQUENCY, TYPE_LENGTHS
from .servers import DEFAULT_MODES, SERVER_MODES, SERVERS, hard_close
from .urscript import RUNNABLE_SAFETY, ControlScript

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
DERIVED = (
    "timestamp",
    "target_q",
    "actual_TCP_pose",
    "target_TCP_pose",
    "robot_status_bits",
    "safety_status_bits",
    "safety_status",
    "runtime_state",
    "speed_scaling",
)


def _rtde_defaults() -> dict:
    """Plausible idle values for every RTDE output (a UR3e powered, brakes released, at rest)."""
    values = {}
    for name, typ in OUTPUT_TYPES.items():
        n = TYPE_LENGTHS.get(typ)
        values[name] = [0.0 if typ.endswith("D") else 0] * n if n else (False if typ == "BOOL" else 0)
        if typ in ("DOUBLE",):
            values[name] = 0.0
    values.update(
        {
            "actual_q": list(HOME_Q),
            "joint_temperatures": [31.2, 32.0, 31.6, 33.1, 33.4, 32.8],
            "actual_execution_time": 0.12,
            "robot_mode": 7,
            "safety_mode": 1,
            "joint_mode": [253] * 6,
            "actual_tool_accelerometer": [0.0, 0.0, 9.81],
            "target_speed_fraction": 1.0,
            "actual_main_voltage": 48.1,
            "actual_robot_voltage": 47.9,
            "actual_robot_current": 0.45,
            "actual_joint_voltage": [47.8, 47.7, 47.8, 47.9, 47.8, 47.8],
            "tool_mode": 253,
            "tool_output_voltage": 24,
            "tool_temperature": 34.5,
            "io_current": 0.08,
            "payload": 0.9,
            "payload_cog": [0.0, 0.0, 0.06],
            "elbow_position": [0.0, 0.0, 0.0],
            "actual_current": [0.01, -1.2, -0.6, 0.05, 0.02, 0.0],
        }
    )
    values["external_force_torque"] = [0.0] * 6  # an input only; kept so 'get' shows what clients wrote
    for name in DERIVED:
        values[name] = None
    return values


class StateError(ValueError):
    pass


class Controller:
    """Shared robot state, logs and server modes; its one lock also serializes the protocol handlers."""

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

    def apply_pending(self) -> None:
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
        g.advance(time.monotonic(), self.gripper_frozen())
        for key, v in value.items():
            if key in g.config:
                g.config[key] = v
            elif key in g.REGISTERS:
                g.regs[key] = int(v)
            else:
                raise StateError(f"unknown gripper key: {key!r}")

    def gripper_frozen(self) -> bool:
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
            self.apply_pending()
            self.script.advance(time.monotonic())
            self.gripper.advance(time.monotonic(), self.gripper_frozen())
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
            hard_close(conn)
        self.log("control", "drop", target=server, count=len(conns))
        return len(conns)
