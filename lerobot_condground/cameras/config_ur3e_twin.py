"""`type: ur3e_twin` cameras: renders of the twin's scene for `--robot.type=ur3e --robot.backend=sim`."""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.cameras import CameraConfig

TWIN_CAMERAS = ("top", "wrist")


@CameraConfig.register_subclass("ur3e_twin")
@dataclass(kw_only=True)
class UR3eTwinCameraConfig(CameraConfig):
    # A camera of the twin's scene: top (across the table, as in simulated datasets) or wrist.
    camera: str = "top"
    width: int | None = 320
    height: int | None = 240
    fps: int | None = 20

    def __post_init__(self):
        from lerobot_condground.envs.arm_env import check_resolution

        if self.camera not in TWIN_CAMERAS:
            raise ValueError(f"ur3e_twin camera={self.camera!r}; allowed: {', '.join(TWIN_CAMERAS)}")
        check_resolution(self.height, self.width)
