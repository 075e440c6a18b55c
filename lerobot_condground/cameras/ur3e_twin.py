"""A LeRobot camera that renders the connected UR3e twin's scene (MuJoCo, headless with EGL)."""

from __future__ import annotations

import mujoco
import numpy as np
from lerobot.cameras import Camera

from .config_ur3e_twin import TWIN_CAMERAS, UR3eTwinCameraConfig

# The connected twins of this process: a ur3e robot with the sim backend adds itself on connect, so the
# camera finds the scene it renders without importing the robot (cameras sit below robots).
TWINS: list = []


def active_twin():
    if len(TWINS) != 1:
        raise RuntimeError(
            f"{len(TWINS)} ur3e twins are connected in this process; ur3e_twin cameras and the ur3e_expert "
            "teleoperator need exactly one --robot.type=ur3e --robot.backend=sim robot, connected first"
        )
    return TWINS[0]


class UR3eTwinCamera(Camera):
    def __init__(self, config: UR3eTwinCameraConfig):
        super().__init__(config)
        self.config = config
        self._twin = None
        self._renderer = None
        self._model = None

    def __str__(self) -> str:
        return f"UR3eTwinCamera({self.config.camera})"

    @property
    def is_connected(self) -> bool:
        return self._twin is not None

    @staticmethod
    def find_cameras() -> list[dict]:
        return [{"name": cam, "type": "ur3e_twin"} for cam in TWIN_CAMERAS] if TWINS else []

    def connect(self, warmup: bool = True) -> None:
        self._twin = active_twin()
        if warmup:
            self.read()

    def read(self, color_mode=None) -> np.ndarray:
        if self._twin is None:
            raise RuntimeError(f"{self} is not connected")
        twin = self._twin
        with twin.lock:
            if twin.env is None:
                raise RuntimeError(f"{self}: the twin it renders was disconnected")
            if self._model is not twin.env.model:  # a new layout may bring a rebuilt model
                if self._renderer is not None:
                    self._renderer.close()
                self._model = twin.env.model
                self._renderer = mujoco.Renderer(self._model, self.config.height, self.config.width)
            self._renderer.update_scene(twin.env.data, camera=self.config.camera)
            return self._renderer.render().copy()

    def async_read(self, timeout_ms: float = 200) -> np.ndarray:
        return self.read()

    def read_latest(self, max_age_ms: int = 500) -> np.ndarray:
        return self.read()

    def disconnect(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
        self._renderer = self._model = self._twin = None
