"""The dashboard server (port 29999): its one-line text protocol."""

from __future__ import annotations

import os
import socket
import threading
import time
from typing import TYPE_CHECKING

from .arm import ROBOT_MODES, SAFETY_MODES
from .servers import SERVERS, read_lines

if TYPE_CHECKING:
    from .state import Controller


def dashboard_command(ctl: Controller, line: str) -> tuple[str, bool]:
    """One request line -> (response line, close connection afterwards)."""
    cmd = line.strip()
    with ctl.lock:
        ctl.apply_pending()
        ctl.dashboard_log.append(cmd)
        ctl.script.advance(time.monotonic())
        if cmd.startswith("load "):  # loading a program stops a script sent to port 30003
            ctl.script.end(f"dashboard {cmd}")
        response, close = _answer(ctl, cmd)
        ctl.script.advance(time.monotonic())  # 'stop' / 'power off' end the script at once
    ctl.log("dashboard", "command", command=cmd, response=response)
    return response, close


def _answer(ctl: Controller, cmd: str) -> tuple[str, bool]:
    s, now = ctl.state, time.monotonic()
    program = s["loaded_program"]
    if cmd == "quit":
        return "Disconnected", True
    if cmd == "shutdown":
        threading.Thread(target=_shutdown_servers, args=(ctl,), daemon=True).start()
        return "Shutting down", True
    if cmd.startswith("load installation "):
        return f"Loading installation: {cmd[len('load installation ') :].strip()}", False
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
        if program is None and ctl.script.starts == 0:
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
        return ("Added log message" if cmd[len("addToLog") :].strip() else "No log message to add"), False
    if cmd == "isProgramSaved":
        return f"{str(bool(s['program_saved'])).lower()} {_program_name(program)}", False
    if cmd == "programState":
        return f"{s['program_state']} {_program_name(program)}", False
    if cmd == "PolyscopeVersion":
        return f"URSoftware {s['software_version']} ({s['software_build_date']})", False
    if cmd == "version":
        return f"Version information: {s['software_version']}", False
    if cmd.startswith("setUserRole "):
        return f"Setting user role: {cmd[len('setUserRole ') :].strip()}", False
    if cmd == "power on":
        if s["robot_mode"] in (3, 0, 1):
            s["robot_mode"] = 4
            ctl.pending.append((now + s["power_on_delay_s"], "robot_mode", 5))
        return "Powering on", False
    if cmd == "power off":
        s["robot_mode"], s["program_state"] = 3, "STOPPED"
        ctl.pending = [p for p in ctl.pending if p[1] != "robot_mode"]
        return "Powering off", False
    if cmd == "brake release":
        if s["robot_mode"] in (4, 5):
            ctl.pending.append((now + s["brake_release_delay_s"], "robot_mode", 7))
        return "Brake releasing", False
    if cmd == "safetymode":
        return f"Safetymode: {SAFETY_MODES.get(s['safety_mode'], str(s['safety_mode']))}", False
    if cmd == "safetystatus":
        status = ctl.value("safety_status")
        return f"Safetystatus: {SAFETY_MODES.get(status, str(status))}", False
    if cmd == "unlock protective stop":
        if s["safety_mode"] == 3:
            since = now - (ctl.protective_stop_at or 0.0)
            if since < s["protective_stop_unlock_delay_s"]:
                return (
                    "Cannot unlock protective stop until 5s after occurrence. "
                    "Always inspect cause of protective stop before unlocking"
                ), False
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
        mode = cmd[len("set operational mode ") :].strip()
        s["operational_mode"] = mode.upper()
        return f"Operational mode '{mode}' is set", False
    if cmd == "clear operational mode":
        return (
            "No longer controlling the operational mode. "
            f"Current operational mode: '{str(s['operational_mode']).lower()}'."
        ), False
    return f"could not understand: '{cmd}'", False


def _shutdown_servers(ctl: Controller) -> None:
    time.sleep(0.05)  # let the "Shutting down" reply leave first
    for server in SERVERS:
        if ctl.modes[server] != "off":
            ctl.set_mode(server, "off")
        ctl.drop(server)


def _program_name(program) -> str:
    return os.path.basename(program) if program else "<unnamed>"


def serve_dashboard(ctl: Controller, conn: socket.socket, peer) -> None:
    ctl.log("dashboard", "connect", peer=f"{peer[0]}:{peer[1]}")
    conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
    for line in read_lines(conn):
        response, close = dashboard_command(ctl, line)
        conn.sendall(response.encode() + b"\n")
        if close:
            break
    ctl.log("dashboard", "disconnect", peer=f"{peer[0]}:{peer[1]}")
