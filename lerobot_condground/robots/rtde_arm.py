"""The UR3e through ur_rtde, in a process of its own.

ur_rtde's native calls hold the GIL while they block, and its connect has no timeout: in LeRobot's
process they would freeze the camera threads and could hang a script forever. So a spawned worker
process owns every ur_rtde object and runs the 500 Hz servo loop (`ServoLoop` over `URBackend`); the
robot talks to it through a pipe (commands in, faults out) and reads the arm's state from shared
memory. The parent waits for the worker with timeouts and kills it when it does not answer.

The worker always leaves the arm stopped: on disconnect, on a fault, when the parent dies (pipe
closed), on SIGTERM; it ignores Ctrl-C so the parent's orderly disconnect is what runs.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import signal
import socket
import threading
import time
from dataclasses import asdict

import numpy as np

from .safety import ArmFault, check_safety_mode
from .servo_loop import ArmState, ServoLoop

logger = logging.getLogger(__name__)

DASHBOARD_PORT, RTDE_PORT = 29999, 30004
_STATE_SIZE = 6 + 6 + 6  # q, qd, gripper, safety_mode, streaming, freedrive, stalls, time
_SCRIPT_STOPPED = (
    "The UR control script stopped (a stop on the pendant, a safety stop, or another program); the "
    "arm no longer follows commands. Check the pendant, then reconnect."
)


def probe(host: str, port: int, timeout: float) -> None:
    """A plain TCP connect with a timeout, before any ur_rtde call (those have none)."""
    try:
        with socket.create_connection((host, port), timeout=timeout):
            pass
    except OSError as exc:
        raise ConnectionError(
            f"UR controller {host}:{port} is unreachable ({exc}). Check the address (--robot.host), the cable "
            "and that this PC is on the robot's subnet; the controller must be powered on."
        ) from exc


@contextlib.contextmanager
def answering(host: str, port: int, what: str):
    """ur_rtde's own errors for a controller that accepts and then stays silent say only `Operation canceled`."""
    try:
        yield
    except ConnectionError:
        raise
    except Exception as exc:
        raise ConnectionError(
            f"UR controller {host}:{port} ({what}) accepted the connection but did not answer ({type(exc).__name__}: "
            f"{exc}). Check that the controller has finished booting (the pendant shows the robot's screen), that "
            "no other program holds this interface, and that --robot.host is the controller, not another device."
        ) from exc


class URBackend:
    """ArmBackend over ur_rtde, inside the worker process."""

    def __init__(self, cfg: dict):
        self.cfg = cfg
        self.receive = self.control = self.dashboard = self.gripper = None
        self.servo_period = 1.0 / cfg["servo_hz"]
        self._gripper_target: float | None = None
        self._gripper_closure = 0.0
        self._gripper_error: BaseException | None = None
        self._running = True

    def connect(self) -> None:
        import dashboard_client
        import rtde_receive

        cfg, host = self.cfg, self.cfg["host"]
        with answering(host, DASHBOARD_PORT, "dashboard server"):
            self.dashboard = dashboard_client.DashboardClient(host)
            self.dashboard.connect()
            model = self.dashboard.getRobotModel().strip()
        if model != cfg["expected_model"]:
            raise ConnectionError(
                f"The dashboard at {host} reports robot model {model!r}; --robot.type=ur3e drives a UR3e "
                f"(dashboard model {cfg['expected_model']!r}). Its limits and kinematics would be wrong for this arm."
            )
        if not cfg["dry_run"] and not self.dashboard.isInRemoteControl():
            raise ConnectionError(
                f"The UR at {host} is in Local Control. Switch the teach pendant to Remote Control "
                "(Settings > System > Remote Control, then the pendant's top-right toggle)."
            )
        with answering(host, RTDE_PORT, "RTDE interface"):
            self.receive = rtde_receive.RTDEReceiveInterface(host, cfg["servo_hz"])
            safety_mode = self.receive.getSafetyMode()
        check_safety_mode(safety_mode)
        if not cfg["dry_run"]:
            import rtde_control

            with answering(host, RTDE_PORT, "RTDE control interface"):
                self.control = rtde_control.RTDEControlInterface(host)
        if cfg["gripper"] == "robotiq":
            from .grippers import RobotiqSocketGripper

            self.gripper = RobotiqSocketGripper(
                host, cfg["gripper_port"], cfg["gripper_speed"], cfg["gripper_force"]
            )
            self.gripper.connect(activate=not cfg["dry_run"])
            self._gripper_closure = self.gripper.closure()  # the first observation is already right
            threading.Thread(target=self._gripper_io, name="robotiq", daemon=True).start()
        elif cfg["gripper"] == "digital_output":
            from .grippers import DigitalOutputGripper

            self.gripper = DigitalOutputGripper(host, cfg["gripper_output"])
            if not cfg["dry_run"]:
                self.gripper.connect()

    def _gripper_io(self) -> None:
        # The socket round trip (~1 ms) must not stall the 500 Hz loop: commands and readings go here.
        try:
            while self._running:
                target, self._gripper_target = self._gripper_target, None
                if target is not None and not self.cfg["dry_run"]:
                    self.gripper.command(target)
                self._gripper_closure = self.gripper.closure()
                time.sleep(0.02)
        except BaseException as exc:
            self._gripper_error = exc

    def read(self):
        if self._gripper_error is not None:
            raise ArmFault(f"Gripper connection lost: {self._gripper_error}")
        if self.cfg["gripper"] == "digital_output":
            self._gripper_closure = self.gripper.closure_from_bits(self.receive.getActualDigitalOutputBits())
        if not self.receive.isConnected():
            raise ArmFault(f"Lost the RTDE connection to {self.cfg['host']}; the controller stops the arm")
        return (
            np.array(self.receive.getActualQ()),
            np.array(self.receive.getActualQd()),
            self._gripper_closure,
            self.receive.getSafetyMode(),
        )

    def servo(self, q) -> None:
        if self.control is not None and not self.control.servoJ(
            list(q), 0.0, 0.0, self.servo_period, self.cfg["servoj_lookahead_time"], self.cfg["servoj_gain"]
        ):
            # ur_rtde answers False, silently, once the control script has stopped (stop pressed on the
            # pendant, a safety stop): the arm no longer follows, and must not be thought to.
            raise ArmFault(_SCRIPT_STOPPED)

    def servo_stop(self) -> None:
        if self.control is not None:
            self.control.servoStop(2.0)

    def set_gripper(self, closure: float) -> None:
        if self.cfg["gripper"] == "robotiq":
            self._gripper_target = closure
        elif self.cfg["gripper"] == "digital_output" and not self.cfg["dry_run"]:
            self.gripper.command(closure)

    def freedrive(self, on: bool) -> None:
        if self.control is None:
            raise ValueError("Freedrive needs the control interface; it is off with --robot.dry_run=true")
        if not (self.control.teachMode() if on else self.control.endTeachMode()):
            raise ArmFault(_SCRIPT_STOPPED)

    def start_period(self):
        return self.control.initPeriod() if self.control is not None else time.perf_counter()

    def wait_period(self, start) -> None:
        if self.control is not None:
            self.control.waitPeriod(start)
        else:
            time.sleep(max(0.0, self.servo_period - (time.perf_counter() - start)))

    def close(self) -> None:
        self._running = False
        for step in (
            lambda: self.control and self.control.servoStop(2.0),
            lambda: self.control and self.control.endTeachMode(),
            lambda: self.control and self.control.stopScript(),
            lambda: self.control and self.control.disconnect(),
            lambda: self.receive and self.receive.disconnect(),
            lambda: self.gripper and self.gripper.close(),
            lambda: self.dashboard and self.dashboard.disconnect(),
        ):
            try:
                step()
            except Exception as exc:  # keep closing the rest; the arm is already told to stop first
                logger.warning("ur3e worker: while closing: %s", exc)


def _publish(shared, state: ArmState) -> None:
    with shared.get_lock():
        shared[:] = [
            *state.q,
            *state.qd,
            state.gripper,
            state.safety_mode,
            state.streaming,
            state.freedrive,
            state.stalls,
            state.time,
        ]


def _exit(*_) -> None:
    raise SystemExit(0)  # unwinds through the worker's finally, which stops the arm


def _worker(cfg: dict, conn, shared) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it disconnects in order
    signal.signal(signal.SIGTERM, _exit)
    backend = URBackend(cfg)
    try:
        backend.connect()
        loop = ServoLoop(
            backend,
            control_period=1 / cfg["control_hz"],
            servo_period=1 / cfg["servo_hz"],
            max_joint_velocity=np.array(cfg["max_joint_velocity"]),
            joint_min=np.array(cfg["joint_min"]),
            joint_max=np.array(cfg["joint_max"]),
            stall_periods=cfg["stall_periods"],
        )
        _publish(shared, loop.state)
        conn.send(("ready", None))
        t0 = time.perf_counter()
        while True:
            start = backend.start_period()
            now = time.perf_counter() - t0
            while conn.poll():
                msg = conn.recv()
                if msg[0] == "command":
                    loop.command(msg[1], msg[2], now)
                elif msg[0] == "freedrive":
                    loop.set_freedrive(msg[1])
                elif msg[0] == "stop":
                    loop.stop()
                elif msg[0] == "close":
                    return
            _publish(shared, loop.tick(now))
            backend.wait_period(start)
    except EOFError:
        pass  # the parent is gone: stop the arm (finally) and exit
    except ArmFault as exc:
        conn.send(("fault", str(exc)))
    except BaseException as exc:
        with contextlib.suppress(OSError):
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        backend.close()


class RTDEArm:
    def __init__(self, config):
        self.config = config
        self.process = None
        self.conn = None
        self.shared = None
        self._fault: str | None = None

    @property
    def is_connected(self) -> bool:
        # Until disconnect(): a faulted arm stays "connected" so every call reports the fault.
        return self.process is not None

    def _worker_config(self) -> dict:
        cfg = asdict(self.config)
        keep = (
            "host",
            "servo_hz",
            "control_hz",
            "servoj_lookahead_time",
            "servoj_gain",
            "gripper",
            "gripper_port",
            "gripper_speed",
            "gripper_force",
            "gripper_output",
            "expected_model",
            "dry_run",
            "joint_min",
            "joint_max",
            "max_joint_velocity",
            "stall_periods",
        )
        return {k: cfg[k] for k in keep}

    def connect(self) -> None:
        cfg = self.config
        for port in (DASHBOARD_PORT, RTDE_PORT):
            probe(cfg.host, port, min(cfg.connect_timeout_s, 3.0))
        ctx = mp.get_context("spawn")  # a fresh interpreter: no inherited threads or CUDA state
        self.conn, child = ctx.Pipe()
        self.shared = ctx.Array("d", _STATE_SIZE)
        self.process = ctx.Process(
            target=_worker,
            args=(self._worker_config(), child, self.shared),
            name=f"ur3e-arm-worker-{cfg.host}",
            daemon=True,
        )
        self.process.start()
        child.close()
        deadline = time.monotonic() + cfg.connect_timeout_s
        while not self.conn.poll(0.05):
            if not self.process.is_alive() or time.monotonic() > deadline:
                self._kill()
                raise ConnectionError(
                    f"UR controller {cfg.host} (dashboard server {cfg.host}:{DASHBOARD_PORT}, RTDE "
                    f"{cfg.host}:{RTDE_PORT}) accepted the connection but did not finish connecting within "
                    f"{cfg.connect_timeout_s} s. Check that the controller has finished booting, that no other program "
                    "holds these interfaces, and that --robot.host is the controller (--robot.connect_timeout_s sets "
                    "the wait; ur_rtde has none of its own)"
                )
        try:
            kind, message = self.conn.recv()
        except EOFError:
            self._kill()
            raise ConnectionError(
                "The ur3e worker process exited before connecting. In a script of your own, start the robot under "
                '`if __name__ == "__main__":`: the worker is spawned, and spawning re-runs the main module.'
            ) from None
        if kind != "ready":
            self._kill()
            raise ConnectionError(message)

    def _check(self) -> None:
        if self._fault is None and self.conn is not None and self.conn.poll():
            kind, message = self.conn.recv()
            self._fault = message if kind in ("fault", "error") else None
        if self._fault is not None:
            raise ArmFault(self._fault)
        if self.process is None or not self.process.is_alive():
            raise ArmFault("The ur3e worker process is gone; the arm was stopped. Reconnect the robot.")

    def state(self) -> ArmState:
        self._check()
        with self.shared.get_lock():
            v = np.array(self.shared[:])
        return ArmState(
            q=v[0:6],
            qd=v[6:12],
            gripper=float(v[12]),
            safety_mode=int(v[13]),
            streaming=bool(v[14]),
            freedrive=bool(v[15]),
            stalls=int(v[16]),
            time=float(v[17]),
        )

    def _send(self, *msg) -> None:
        self._check()
        self.conn.send(msg)

    def command(self, q, gripper: float) -> None:
        self._send("command", None if q is None else np.asarray(q, float), float(gripper))

    def freedrive(self, on: bool) -> None:
        if on and self.config.dry_run:
            raise ValueError("Freedrive needs the control interface; it is off with --robot.dry_run=true")
        self._send("freedrive", bool(on))

    def stop(self) -> None:
        if self.is_connected:
            self.conn.send(("stop",))

    def disconnect(self) -> None:
        if self.process is None:
            return
        try:
            if self.process.is_alive():
                self.conn.send(("close",))
            self.process.join(timeout=3)
        except OSError:
            pass
        finally:
            self._kill()

    def _kill(self) -> None:
        if self.process is not None and self.process.is_alive():
            self.process.terminate()  # SIGTERM: the worker stops the arm on its way out
            self.process.join(timeout=3)
            if self.process.is_alive():
                self.process.kill()
        self.process = None
