"""The instrument-routing scene: an instrument on the table, two identical containers left and right.

The instrument's visible state (a red contamination mark on its handle, present or not) decides where it
goes by a fixed rule: marked -> left container, unmarked -> right container, left and right as the robot
sees them (its base facing the table along +x: left is +y; the scene camera, facing the robot, shows the
left container on the right of its image).

Segmentation labels (`core/routing.py`): 0 background and robot, 1 instrument, 2 the correct container,
3 the other container, 4 the state-bearing region (the patch of the handle that carries the mark, also
when it is unmarked).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from lerobot_condground.core.routing import (
    DESTINATION,
    DESTINATION_OF,
    INSTRUMENT,
    OTHER_CONTAINER,
    SIDES,
    STATE_REGION,
)

from . import robot
from .assets import FLOOR_THICKNESS, Asset
from .scene import add_receptacle_geoms, workcell_spec

# Instrument: a steel handle with a darker head; the jaw closes across the handle's width.
HANDLE_HALF = (0.034, 0.011, 0.011)  # m, half sizes (length, width, height)
HEAD_HALF = (0.01, 0.016, 0.009)
INSTRUMENT_HEIGHT = 2 * HANDLE_HALF[2]
GRASP_WIDTH = 2 * HANDLE_HALF[1]
MARK_X = -0.018  # mark centre along the handle, from the instrument's centre
MARK_HALF = (0.012, HANDLE_HALF[1] + 0.0004, 0.0012)
STEEL = [0.62, 0.64, 0.68, 1.0]
HEAD = [0.35, 0.37, 0.42, 1.0]
MARK = [0.85, 0.12, 0.10, 1.0]
INSTRUMENT_MASS = 0.06

# Containers: identical bowls (the instrument fits at any yaw), left (+y) and right (-y), jittered by up to CONTAINER_JITTER.
CONTAINER = Asset("receptacle", "bowl", "blue")
CONTAINER_XY = {"left": (0.26, 0.24), "right": (0.26, -0.24)}
CONTAINER_JITTER = 0.02
# Where the instrument starts: a box in front of the robot, between the containers, any yaw in range.
INSTRUMENT_X, INSTRUMENT_Y, INSTRUMENT_YAW = (0.29, 0.37), (-0.07, 0.07), (-0.7, 0.7)

# Tool poses of the procedure: the inspection point faces the scene camera, centred between the containers
# (nothing there tells where the instrument goes); the sorting point is above the containers' midpoint.
INSPECT_POINT = np.array([0.31, 0.0, 0.2])
SORT_HEIGHT = 0.13


@dataclass(frozen=True)
class RoutingLayout:
    contaminated: bool
    instrument_xy: tuple[float, float]
    instrument_yaw: float
    containers: dict  # side -> (x, y)

    @property
    def destination(self) -> str:
        return DESTINATION_OF[self.contaminated]

    @property
    def other(self) -> str:
        return "right" if self.destination == "left" else "left"

    @property
    def sort_point(self) -> np.ndarray:
        mid = (np.array(self.containers["left"]) + np.array(self.containers["right"])) / 2
        return np.array([*mid, SORT_HEIGHT])


def sample_routing_layout(seed: int, contaminated: bool | None = None) -> RoutingLayout:
    """A layout drawn from `seed`; the state too unless given."""
    rng = np.random.default_rng(seed)
    state = bool(rng.integers(2))
    xy = (float(rng.uniform(*INSTRUMENT_X)), float(rng.uniform(*INSTRUMENT_Y)))
    yaw = float(rng.uniform(*INSTRUMENT_YAW))
    containers = {
        side: tuple(float(v) for v in np.array(CONTAINER_XY[side]) + rng.uniform(-1, 1, 2) * CONTAINER_JITTER)
        for side in SIDES
    }
    return RoutingLayout(state if contaminated is None else contaminated, xy, yaw, containers)


def build_routing_model() -> mujoco.MjModel:
    """One model for every layout: poses, and the mark's colour, are set by `apply_routing_layout`."""
    spec = workcell_spec()
    world = spec.worldbody
    body = world.add_body(name="instrument", pos=[0.3, 0.0, HANDLE_HALF[2]])
    body.add_freejoint(name="instrument_free")
    solid = dict(
        contype=robot.BIT_OBJECT,
        conaffinity=robot.BIT_TABLE | robot.BIT_OBJECT | robot.BIT_FINGER,
        friction=[1.0, 0.02, 0.002],
        condim=4,
    )
    body.add_geom(
        name="handle", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(HANDLE_HALF), rgba=STEEL,
        mass=INSTRUMENT_MASS * 0.7, **solid,
    )  # fmt: skip
    body.add_geom(
        name="head", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(HEAD_HALF), rgba=HEAD,
        pos=[HANDLE_HALF[0] + HEAD_HALF[0], 0, HEAD_HALF[2] - HANDLE_HALF[2]], mass=INSTRUMENT_MASS * 0.3,
        **solid,
    )  # fmt: skip
    # A skin over the handle's patch, visual only: red when marked, steel when not.
    body.add_geom(
        name="mark", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(MARK_HALF), rgba=MARK,
        pos=[MARK_X, 0, HANDLE_HALF[2] - MARK_HALF[2] + 0.0004], contype=0, conaffinity=0, density=0,
    )  # fmt: skip
    for side in SIDES:
        container = world.add_body(name=f"container_{side}", pos=[*CONTAINER_XY[side], 0.0])
        add_receptacle_geoms(container, CONTAINER)
    return spec.compile()


def apply_routing_layout(model: mujoco.MjModel, data: mujoco.MjData, layout: RoutingLayout) -> None:
    adr = model.joint("instrument_free").qposadr[0]
    yaw = layout.instrument_yaw
    data.qpos[adr : adr + 7] = [
        *layout.instrument_xy,
        HANDLE_HALF[2] + 1e-4,
        math.cos(yaw / 2),
        0,
        0,
        math.sin(yaw / 2),
    ]
    for side in SIDES:
        model.body_pos[model.body(f"container_{side}").id] = [*layout.containers[side], 0.0]
    model.geom_rgba[model.geom("mark").id] = MARK if layout.contaminated else STEEL


def geom_labels(model: mujoco.MjModel, layout: RoutingLayout) -> np.ndarray:
    """Segmentation label of every geom for this layout (the containers' labels follow the state)."""
    labels = np.zeros(model.ngeom, dtype=np.int32)
    for name in ("handle", "head"):
        labels[model.geom(name).id] = INSTRUMENT
    labels[model.geom("mark").id] = STATE_REGION
    for side, label in ((layout.destination, DESTINATION), (layout.other, OTHER_CONTAINER)):
        body = model.body(f"container_{side}").id
        labels[model.body_geomadr[body] : model.body_geomadr[body] + model.body_geomnum[body]] = label
    return labels


def release_height() -> float:
    """Tool height at which the instrument is let go in a container: its bottom 2 cm above the floor."""
    return FLOOR_THICKNESS + 0.02 + HANDLE_HALF[2]
