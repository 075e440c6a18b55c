"""What every server of the fake shares: the fixed ports and per-server modes, the accept loop, and the
socket and JSON helpers of the protocol handlers."""

from __future__ import annotations

import contextlib
import socket
import threading
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .state import Controller

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
GRIPPER_PORT = 63352
SCRIPT_PORT = 30003  # the realtime interface, where ur_rtde's RTDEControlInterface uploads its script
CONTROL_PORT = 30099
SERVERS = ("rtde", "dashboard", "gripper", "script")
# The script port is off unless asked for, so by default RTDEControlInterface fails at once (connection
# refused) and the plugin's dry-run tests never start a control script. With it on, the fake records what
# arrives and runs ur_rtde's control script (urscript.ControlScript), as a controller would.
DEFAULT_MODES = {"rtde": "serve", "dashboard": "serve", "gripper": "serve", "script": "off"}
# "serve": normal; "refuse": accept then close at once (client sees EOF); "silent": accept, read and
# never answer (client times out); "off": not listening (connection refused).
SERVER_MODES = ("serve", "refuse", "silent", "off")


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
            self.thread = threading.Thread(
                target=self._accept_loop, args=(sock,), daemon=True, name=f"accept-{self.name}"
            )
            self.thread.start()

    def stop(self) -> None:
        """Stops listening; once this returns, new connections are refused (ECONNREFUSED)."""
        with self.lock:
            sock, self.sock, thread = self.sock, None, self.thread
        if sock is None:
            return
        # On Linux this stops the listener at once (pending and new connects are refused), even
        # while the accept thread still sits in poll() on the descriptor.
        with contextlib.suppress(OSError):
            sock.shutdown(socket.SHUT_RDWR)
        if thread is not None:
            thread.join(1.0)  # the fd really closes only when no thread is inside a call on it
        sock.close()

    def _accept_loop(self, sock: socket.socket) -> None:
        while self.sock is sock:
            try:
                conn, peer = sock.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            conn.settimeout(None)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            mode = self.ctl.modes.get(self.name, "serve")
            if mode == "refuse":
                self.ctl.log(self.name, "refused", peer=f"{peer[0]}:{peer[1]}")
                hard_close(conn)
                continue
            threading.Thread(
                target=self._serve, args=(conn, peer, mode), daemon=True, name=f"{self.name}-{peer[1]}"
            ).start()

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
            hard_close(conn)


def read_lines(conn: socket.socket):
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


def jsonable(v):
    return list(v) if isinstance(v, tuple) else v


def hard_close(conn: socket.socket) -> None:
    with contextlib.suppress(OSError):
        conn.shutdown(socket.SHUT_RDWR)
    with contextlib.suppress(OSError):
        conn.close()
