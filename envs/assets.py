"""Colors and shapes of objects and receptacles, and the two disjoint asset pools.

Evaluation scenes draw targets and competitors only from the EVAL pools; training-time augmentation
draws only from the AUGMENTATION pools. The pools share no color and no shape, so no (shape, color)
asset an evaluation competitor can take is ever seen as a synthetic distractor in training.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lerobot_condground.core.conditions import ROLES

COLORS: dict[str, tuple[float, float, float]] = {
    # evaluation palette
    "red": (0.85, 0.12, 0.10),
    "green": (0.15, 0.65, 0.20),
    "blue": (0.12, 0.30, 0.85),
    "yellow": (0.92, 0.82, 0.10),
    # augmentation palette
    "orange": (0.98, 0.50, 0.05),
    "purple": (0.50, 0.20, 0.70),
    "cyan": (0.10, 0.80, 0.85),
    "magenta": (0.90, 0.20, 0.65),
}

EVAL_COLORS = ("red", "green", "blue", "yellow")
AUGMENTATION_COLORS = ("orange", "purple", "cyan", "magenta")

OBJECT_HEIGHT = 0.04
WALL_THICKNESS = 0.006
FLOOR_THICKNESS = 0.006


@dataclass(frozen=True)
class ObjectShape:
    """A graspable block. `grasp_width` is the jaw opening across the grasp; `grasp_period` the
    yaw symmetry of valid grasps (0 = any yaw); `grasp_offset` turns the jaw from the body's x axis."""

    name: str
    footprint: float  # radius of the circle that holds the footprint
    grasp_width: float
    grasp_period: float
    grasp_offset: float = 0.0


@dataclass(frozen=True)
class ReceptacleShape:
    """A container: a floor and walls along a convex polygon given by its inner half-planes."""

    name: str
    normals_deg: tuple[float, ...]  # outward wall normals, in the receptacle frame
    apothems: tuple[float, ...]  # inner distance from the center to each wall
    wall_height: float = 0.035

    @property
    def footprint(self) -> float:
        return max(float(np.hypot(*v)) for v in polygon_vertices(self)) + WALL_THICKNESS


def _regular(n: int, apothem: float, phase_deg: float = 0.0) -> tuple[tuple[float, ...], tuple[float, ...]]:
    return tuple(phase_deg + 360.0 * k / n for k in range(n)), (apothem,) * n


def polygon_vertices(shape: ReceptacleShape) -> list[np.ndarray]:
    """Inner polygon corners: intersections of consecutive wall lines."""
    normals = [np.array([math.cos(math.radians(a)), math.sin(math.radians(a))]) for a in shape.normals_deg]
    verts = []
    for k in range(len(normals)):
        n1, n2 = normals[k], normals[(k + 1) % len(normals)]
        verts.append(
            np.linalg.solve(
                np.stack([n1, n2]), np.array([shape.apothems[k], shape.apothems[(k + 1) % len(normals)]])
            )
        )
    return verts


OBJECT_SHAPES: dict[str, ObjectShape] = {
    s.name: s
    for s in (
        # evaluation shapes
        ObjectShape("cube", footprint=0.029, grasp_width=0.04, grasp_period=math.pi / 2),
        ObjectShape("cylinder", footprint=0.021, grasp_width=0.042, grasp_period=0.0),
        ObjectShape("cross", footprint=0.031, grasp_width=0.06, grasp_period=math.pi / 2),
        ObjectShape(
            "bar", footprint=0.033, grasp_width=0.026, grasp_period=math.pi, grasp_offset=math.pi / 2
        ),
        # augmentation shapes
        ObjectShape("tri_prism", footprint=0.026, grasp_width=0.04, grasp_period=2 * math.pi / 3),
        ObjectShape("hex_prism", footprint=0.024, grasp_width=0.042, grasp_period=math.pi / 3),
        ObjectShape("sphere", footprint=0.022, grasp_width=0.044, grasp_period=0.0),
        ObjectShape("disc", footprint=0.03, grasp_width=0.06, grasp_period=0.0),
    )
}
EVAL_OBJECT_SHAPES = ("cube", "cylinder", "cross", "bar")
AUGMENTATION_OBJECT_SHAPES = ("tri_prism", "hex_prism", "sphere", "disc")

RECEPTACLE_SHAPES: dict[str, ReceptacleShape] = {
    s.name: s
    for s in (
        # evaluation shapes
        ReceptacleShape("bowl", *_regular(16, 0.056)),
        ReceptacleShape("square_bin", *_regular(4, 0.05)),
        ReceptacleShape("hex_bin", *_regular(6, 0.053, 30.0)),
        ReceptacleShape(
            "rect_tray", (0.0, 90.0, 180.0, 270.0), (0.072, 0.05, 0.072, 0.05), wall_height=0.028
        ),
        # augmentation shapes
        ReceptacleShape("tri_bin", *_regular(3, 0.05, 90.0)),
        ReceptacleShape("pentagon_bin", *_regular(5, 0.053, 90.0)),
        ReceptacleShape("plate", *_regular(20, 0.06), wall_height=0.015),
        ReceptacleShape("oct_bin", *_regular(8, 0.054, 22.5)),
    )
}
EVAL_RECEPTACLE_SHAPES = ("bowl", "square_bin", "hex_bin", "rect_tray")
AUGMENTATION_RECEPTACLE_SHAPES = ("tri_bin", "pentagon_bin", "plate", "oct_bin")

POOLS = ("eval", "augmentation")


@dataclass(frozen=True)
class Asset:
    role: str  # "object" | "receptacle"
    shape: str
    color: str

    @property
    def rgba(self) -> list[float]:
        return [*COLORS[self.color], 1.0]

    @property
    def footprint(self) -> float:
        table = OBJECT_SHAPES if self.role == "object" else RECEPTACLE_SHAPES
        return table[self.shape].footprint

    def __str__(self) -> str:
        return f"{self.color} {self.shape.replace('_', ' ')}"


def pool_colors(pool: str) -> tuple[str, ...]:
    return {"eval": EVAL_COLORS, "augmentation": AUGMENTATION_COLORS}[pool]


def pool_shapes(role: str, pool: str) -> tuple[str, ...]:
    return {
        ("object", "eval"): EVAL_OBJECT_SHAPES,
        ("object", "augmentation"): AUGMENTATION_OBJECT_SHAPES,
        ("receptacle", "eval"): EVAL_RECEPTACLE_SHAPES,
        ("receptacle", "augmentation"): AUGMENTATION_RECEPTACLE_SHAPES,
    }[(role, pool)]


def pool_assets(pool: str) -> frozenset[Asset]:
    """Every asset of a pool, both roles."""
    if pool not in POOLS:
        raise ValueError(f"Unknown asset pool {pool!r}; allowed: {', '.join(POOLS)}")
    return frozenset(
        Asset(role, shape, color)
        for role in ROLES
        for shape in pool_shapes(role, pool)
        for color in pool_colors(pool)
    )
