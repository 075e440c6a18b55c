"""The control side channel (port 30099): line-based JSON through which a test changes the robot's state
while real clients are connected, and reads back what the clients did."""

from __future__ import annotations

import json
import os
import socket
from typing import TYPE_CHECKING

from .servers import SERVERS, jsonable, read_lines
from .state import StateError

if TYPE_CHECKING:
    from .state import Controller


def serve_control(ctl: Controller, conn: socket.socket, peer) -> None:
    """Side channel: 'get', 'set {json}', 'mode {json}', 'drop {json}', 'clear', 'ping', 'quit'."""
    for line in read_lines(conn):
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
        conn.sendall(json.dumps(reply, default=jsonable).encode() + b"\n")
