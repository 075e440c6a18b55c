#!/usr/bin/env python3
"""A loopback fake of a UR e-Series controller, faithful at the protocol boundary.

It serves, on one loopback address, what the plugin's UR3e path talks to:

* RTDE (port 30004): the binary "Real-Time Data Exchange" protocol, versions 1 and 2 (ur_rtde speaks 2);
* the dashboard server (port 29999): the one-line text protocol;
* the Robotiq URCap socket (port 63352): "SET ACT 1" / "GET POS" text, with a finger that moves at a
  finite speed and can stop on an object;
* the realtime interface (port 30003, off unless asked for): records the URScript clients send and runs
  ur_rtde's rtde_control script the way the controller would, at the level of the RTDE registers it
  talks through (servoJ, servoStop, teach mode, moveJ, stopScript; see urscript.py), with an arm whose
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

This module only parses the command line and wires the protocol modules of this folder together: servers
(ports, modes, accept loop), state (the shared robot state), rtde, dashboard, gripper, urscript (port 30003)
and side_channel.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys

if not __package__:
    # Run as a script, this folder is sys.path[0]: import its modules as the package ur_fake instead, from
    # the folder above (not as "tests.ur_fake": draccus installs a package named tests).
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from ur_fake.dashboard import serve_dashboard  # noqa: E402
from ur_fake.gripper import serve_gripper  # noqa: E402
from ur_fake.rtde import RtdeSession  # noqa: E402
from ur_fake.servers import (  # noqa: E402
    CONTROL_PORT,
    DASHBOARD_PORT,
    GRIPPER_PORT,
    RTDE_PORT,
    SCRIPT_PORT,
    SERVER_MODES,
    SERVERS,
    Listener,
)
from ur_fake.side_channel import serve_control  # noqa: E402
from ur_fake.state import Controller  # noqa: E402
from ur_fake.urscript import serve_script  # noqa: E402


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
    p.add_argument(
        "--mode",
        action="append",
        default=[],
        metavar="SERVER=MODE",
        help=f"start a server in a mode: {', '.join(SERVER_MODES)}",
    )
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
    print(
        "READY " + json.dumps({"host": args.host, "pid": os.getpid(), "ports": ports, "modes": ctl.modes}),
        flush=True,
    )
    parent = os.getppid()
    while not ctl.stop_event.wait(0.25):
        if args.exit_with_parent and os.getppid() != parent:
            break
    return 0


if __name__ == "__main__":
    sys.exit(main())
