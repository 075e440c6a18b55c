"""The realtime interface (port 30003): records the URScript clients send and runs ur_rtde's control script,
emulated at the level of the RTDE registers it talks through."""

from __future__ import annotations

import collections
import math
import re
import socket
import time
from typing import TYPE_CHECKING

from .arm import ROBOT_MODES, SAFETY_MODES

if TYPE_CHECKING:
    from .state import Controller

# RTDEControlInterface uploads rtde_control.script to port 30003 and talks to it only through RTDE
# registers (offset 0, or 24 with FLAG_UPPER_RANGE_REGISTERS):
#   input_int_register_0       command id (0 = none); input_int_register_1 the 'async' flag
#   input_double_register_0..  arguments (servoJ: q 0-5, speed 6, acceleration 7, time 8, lookahead 9,
#                              gain 10)
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
CMD_NAMES = {
    CMD_MOVEJ: "movej",
    CMD_SERVOJ: "servoj",
    CMD_SPEED_STOP: "speed_stop",
    CMD_SERVO_STOP: "servo_stop",
    CMD_TEACH_MODE: "teach_mode",
    CMD_END_TEACH_MODE: "end_teach_mode",
    CMD_PROTECTIVE_STOP: "protective_stop",
    CMD_STOPL: "stopl",
    CMD_STOPJ: "stopj",
    CMD_STOP_SCRIPT: "stop_script",
}
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

    def __init__(self, ctl: Controller):
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
        self.servo = {
            "target": None,
            "speed": 0.0,
            "acceleration": 0.0,
            "time": 0.002,
            "lookahead": 0.1,
            "gain": 300.0,
        }
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
        self.servo = {
            "target": None,
            "speed": 0.0,
            "acceleration": 0.0,
            "time": 0.002,
            "lookahead": 0.1,
            "gain": 300.0,
        }
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
        if (
            self.running
            and values.get(key) == CMD_SERVOJ
            and self.busy is None
            and self.ctl.state["program_state"] == "PLAYING"
        ):
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
            self.servo = {
                "target": [self._in_double(i) for i in range(6)],
                "speed": self._in_double(6),
                "acceleration": self._in_double(7),
                "time": self._in_double(8),
                "lookahead": self._in_double(9),
                "gain": self._in_double(10),
            }
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
            "control_script": {
                "running": self.running,
                "starts": self.starts,
                "register_offset": self.offset,
                "executing": self.executing,
                "busy": self.busy,
                "motion": self.motion,
                "last_cmd": self.last_cmd,
                "end_reason": self.end_reason,
            },
        }


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
