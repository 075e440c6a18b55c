"""Scene layouts: which assets stand where, drawn from a seeded generator.

Paired by construction: the target object and the target receptacle are drawn first and from their
own generator streams, so a condition with competitors has the same target poses as `clean` under
the same seed; competitors are added around them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lerobot_condground.core.conditions import MATCHES, ROLES, ConditionSpec, check_task

from .assets import (
    OBJECT_SHAPES,
    POOLS,
    Asset,
    pool_colors,
    pool_shapes,
)

# Where entity centers may stand: a sector of an annulus around the robot base, in reach of a
# top-down grasp (checked by the IK test) and in view of the scene camera.
R_MIN, R_MAX = 0.24, 0.42
ANGLE_MAX = math.radians(95.0)
# Task 1's receptacle stands here (polar 0.32 m, -50 deg).
FIXED_RECEPTACLE_XY = (0.32 * math.cos(math.radians(-50)), 0.32 * math.sin(math.radians(-50)))
GAP = 0.012  # free space between any two footprints
FINGER = 0.014  # finger thickness plus margin, beside the opened jaw
PREGRASP_MARGIN = 0.022  # the jaw opens this much wider than the grasp
DEFAULT_TARGET_OBJECT = ("cube", "red")
DEFAULT_TARGET_RECEPTACLE = ("bowl", "blue")
MAX_ATTEMPTS = 100
# Random sequential placement of disks jams near this area fraction: above it, refuse without trying.
MAX_DENSITY = 0.55


class LayoutError(ValueError):
    pass


@dataclass(frozen=True)
class Entity:
    label: int  # segmentation label: 1 target object, 2 target receptacle, 3.. competitors
    asset: Asset
    match: str  # "target" | "color" | "shape" | "neither"
    xy: tuple[float, float]
    yaw: float

    @property
    def is_target(self) -> bool:
        return self.match == "target"

    @property
    def clearance(self) -> float:
        """Radius kept free around the entity: objects include the opened jaw."""
        if self.asset.role == "object":
            shape = OBJECT_SHAPES[self.asset.shape]
            return max(shape.footprint, (shape.grasp_width + PREGRASP_MARGIN) / 2 + FINGER)
        return self.asset.footprint


@dataclass(frozen=True)
class Layout:
    task: str
    entities: tuple[Entity, ...]

    @property
    def target_object(self) -> Entity:
        return self.entities[0]

    @property
    def target_receptacle(self) -> Entity:
        return self.entities[1]

    @property
    def asset_key(self) -> tuple:
        return tuple((e.asset, e.label) for e in self.entities)

    def task_description(self) -> str:
        return f"Pick the {self.target_object.asset} and place it in the {self.target_receptacle.asset}."


def check_competitor_pool(pool: str, flag: str = "competitor_pool") -> str:
    if pool not in POOLS:
        raise ValueError(f"{flag}={pool!r} is not allowed; allowed: {', '.join(POOLS)}")
    return pool


def choose_assets(
    spec: ConditionSpec, counterbalanced: bool, rng: np.random.Generator, competitor_pool: str = "eval"
) -> list[tuple[Asset, str]]:
    """The target object, the target receptacle, then one asset per competitor with its match class.

    Competitors from the `augmentation` pool match their target as the copy-paste step's pastes do: a color
    match is an augmentation shape in the target's color, a shape match the target's shape in an augmentation
    color, neither both from the pool (drawn afresh each layout); so no competitor is ever one an evaluation
    scene can hold, and recording among them is copy-paste rendered in 3D: shading, shadows, contact."""
    check_competitor_pool(competitor_pool)
    colors = list(pool_colors("eval"))
    out: list[tuple[Asset, str]] = []
    targets = {}
    for role, default in (("object", DEFAULT_TARGET_OBJECT), ("receptacle", DEFAULT_TARGET_RECEPTACLE)):
        shapes = list(pool_shapes(role, "eval"))
        if counterbalanced:
            shape, color = shapes[rng.integers(len(shapes))], colors[rng.integers(len(colors))]
        else:
            shape, color = default
        targets[role] = Asset(role, shape, color)
        out.append((targets[role], "target"))
    for role in ROLES:
        target = targets[role]
        if competitor_pool == "augmentation":
            other_shapes = list(rng.permutation(pool_shapes(role, "augmentation")))
            other_colors = list(rng.permutation(pool_colors("augmentation")))
        else:
            other_shapes = [s for s in pool_shapes(role, "eval") if s != target.shape]
            other_colors = [c for c in colors if c != target.color]
            if counterbalanced:
                other_shapes = list(rng.permutation(other_shapes))
                other_colors = list(rng.permutation(other_colors))
        for match in MATCHES:
            for k in range(spec.count(role, match)):
                if match == "color":
                    asset = Asset(role, other_shapes[k], target.color)
                elif match == "shape":
                    asset = Asset(role, target.shape, other_colors[k])
                else:
                    asset = Asset(role, other_shapes[(k + 1) % 3], other_colors[(k + 2) % 3])
                out.append((asset, match))
    return out


def _sample_xy(rng: np.random.Generator) -> np.ndarray:
    r = math.sqrt(rng.uniform(R_MIN**2, R_MAX**2))
    a = rng.uniform(-ANGLE_MAX, ANGLE_MAX)
    return np.array([r * math.cos(a), r * math.sin(a)])


def sample_layout(
    task: str, spec: ConditionSpec, counterbalanced: bool, seed: int, competitor_pool: str = "eval"
) -> Layout:
    """Draws a layout; the same (task, spec, counterbalanced, seed, competitor_pool) always gives the same layout."""
    check_task(task)
    streams = np.random.SeedSequence(seed).spawn(3)
    asset_rng, target_rng, competitor_rng = (np.random.default_rng(s) for s in streams)
    assets = choose_assets(spec, counterbalanced, asset_rng, competitor_pool)
    # Targets first, from their own stream: identical poses across conditions for one seed.
    for _ in range(MAX_ATTEMPTS):
        if task == "PickPlaceFixedBin-v0":
            rec_xy, rec_yaw = np.array(FIXED_RECEPTACLE_XY), 0.0
        else:
            rec_xy, rec_yaw = _sample_xy(target_rng), float(target_rng.uniform(0, 2 * math.pi))
        obj_xy, obj_yaw = _sample_xy(target_rng), float(target_rng.uniform(0, 2 * math.pi))
        placed = [
            Entity(1, assets[0][0], "target", tuple(obj_xy), obj_yaw),
            Entity(2, assets[1][0], "target", tuple(rec_xy), rec_yaw),
        ]
        if _separated(placed[0], placed[1]):
            break
    else:  # pragma: no cover - the two targets alone always fit
        raise LayoutError("could not place the target object and receptacle apart")
    # Competitors: restart the competitor placement from scratch when one cannot be placed.
    for _ in range(MAX_ATTEMPTS):
        entities = list(placed)
        for label, (asset, match) in enumerate(assets[2:], start=3):
            for _ in range(MAX_ATTEMPTS):
                candidate = Entity(
                    label,
                    asset,
                    match,
                    tuple(_sample_xy(competitor_rng)),
                    float(competitor_rng.uniform(0, 2 * math.pi)),
                )
                if all(_separated(candidate, other) for other in entities):
                    entities.append(candidate)
                    break
            else:
                break
        if len(entities) == len(assets):
            return Layout(task, tuple(entities))
    raise LayoutError(
        f"Condition {spec.name!r} does not fit on the table: {len(assets)} entities "
        f"({spec.num_competitors} competitors) could not be placed apart in {MAX_ATTEMPTS} tries; "
        f"use fewer competitors"
    )


def _separated(a: Entity, b: Entity) -> bool:
    return math.dist(a.xy, b.xy) >= a.clearance + b.clearance + GAP


def _max_clearance(role: str, pool: str) -> float:
    return max(
        Entity(0, Asset(role, shape, "red"), "target", (0.0, 0.0), 0.0).clearance
        for shape in pool_shapes(role, pool)
    )


def check_fits(
    task: str, spec: ConditionSpec, counterbalanced: bool, seeds: int = 3, competitor_pool: str = "eval"
) -> None:
    """Raises LayoutError before any work starts when the condition cannot be laid out."""
    check_competitor_pool(competitor_pool)
    n = {role: 1 + sum(spec.count(role, m) for m in MATCHES) for role in ROLES}
    need = sum(
        math.pi * (_max_clearance(role, "eval") + GAP / 2) ** 2
        + (n[role] - 1) * math.pi * (_max_clearance(role, competitor_pool) + GAP / 2) ** 2
        for role in n
    )
    # Area the disks can cover: the sector of centers grown by a typical clearance.
    grow = 0.06
    span = 2 * ANGLE_MAX
    area = (
        0.5 * span * (R_MAX**2 - R_MIN**2)
        + grow * (span * (R_MAX + R_MIN) + 2 * (R_MAX - R_MIN))
        + math.pi * grow**2
    )
    if need > MAX_DENSITY * area:
        raise LayoutError(
            f"Condition {spec.name!r} does not fit on the table: {sum(n.values())} entities "
            f"({spec.num_competitors} competitors) need {need:.3f} m^2 of the {area:.3f} m^2 workspace "
            f"(at most {MAX_DENSITY:.0%} can be filled); use fewer competitors"
        )
    for seed in range(seeds):
        sample_layout(task, spec, counterbalanced, seed, competitor_pool)
