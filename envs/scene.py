"""The table scene around the arm: table, lights, cameras, and one body per layout entity."""

from __future__ import annotations

import math

import mujoco
import numpy as np

from . import robot
from .assets import (
    FLOOR_THICKNESS,
    OBJECT_HEIGHT,
    OBJECT_SHAPES,
    RECEPTACLE_SHAPES,
    WALL_THICKNESS,
    Asset,
    polygon_vertices,
)
from .layout import Layout

PHYSICS_DT = 0.002
MAX_RENDER_HEIGHT, MAX_RENDER_WIDTH = 480, 640
OBJECT_MASS = 0.05
TABLE_RGBA = [0.62, 0.58, 0.52, 1.0]


def entity_body_name(label: int) -> str:
    return f"entity{label}"


def workcell_spec() -> mujoco.MjSpec:
    """What every task shares: physics options, the table, the light, the scene camera `top`, the arm with
    its gripper and the `wrist` camera. Tasks add their bodies to the world and compile."""
    spec = mujoco.MjSpec()
    spec.compiler.degree = False
    spec.option.timestep = PHYSICS_DT
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 10.0
    spec.visual.global_.offwidth = MAX_RENDER_WIDTH
    spec.visual.global_.offheight = MAX_RENDER_HEIGHT
    spec.visual.quality.shadowsize = 1024
    spec.visual.headlight.ambient = [0.35, 0.35, 0.35]
    spec.visual.headlight.diffuse = [0.45, 0.45, 0.45]

    world = spec.worldbody
    world.add_geom(
        name="table",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[0.45, 0.75, 0.02],
        pos=[0.15, 0.0, -0.02],
        rgba=TABLE_RGBA,
        contype=robot.BIT_TABLE,
        conaffinity=robot.BIT_OBJECT | robot.BIT_FINGER,
    )
    world.add_light(pos=[0.3, 0.0, 1.5], dir=[0, 0, -1], diffuse=[0.5, 0.5, 0.5], castshadow=False)
    # Scene camera across the table, facing the robot: the arm rarely hides the workspace from it.
    _add_lookat_camera(world, "top", eye=(0.78, 0.0, 0.92), target=(0.17, 0.0, 0.0), fovy=52.0)
    robot.add_ur3e(spec)
    spec.body("flange").add_camera(
        name="wrist", pos=[0.0, -0.06, 0.04], quat=_quat_from_euler(0, math.pi, 0), fovy=75.0
    )
    return spec


def build_model(layout: Layout) -> mujoco.MjModel:
    """Compiles the scene for a layout's assets. Poses are set later (`apply_layout`), so a model
    can be reused for every layout with the same assets."""
    spec = workcell_spec()
    world = spec.worldbody
    for entity in layout.entities:
        body = world.add_body(name=entity_body_name(entity.label), pos=[*entity.xy, 0.0])
        if entity.asset.role == "object":
            body.add_freejoint(name=f"{entity_body_name(entity.label)}_free")
            _add_object_geoms(spec, body, entity.asset, entity.label)
        else:
            add_receptacle_geoms(body, entity.asset)
    return spec.compile()


def apply_layout(model: mujoco.MjModel, data: mujoco.MjData, layout: Layout) -> None:
    """Poses every entity of `layout` (its assets must match the model's)."""
    for entity in layout.entities:
        name = entity_body_name(entity.label)
        quat = [math.cos(entity.yaw / 2), 0.0, 0.0, math.sin(entity.yaw / 2)]
        if entity.asset.role == "object":
            adr = model.joint(f"{name}_free").qposadr[0]
            data.qpos[adr : adr + 7] = [*entity.xy, OBJECT_HEIGHT / 2 + 1e-4, *quat]
        else:
            model.body_pos[model.body(name).id] = [*entity.xy, 0.0]
            model.body_quat[model.body(name).id] = quat


def _add_object_geoms(spec: mujoco.MjSpec, body, asset: Asset, label: int) -> None:
    h = OBJECT_HEIGHT / 2
    common = dict(
        rgba=asset.rgba,
        contype=robot.BIT_OBJECT,
        conaffinity=robot.BIT_TABLE | robot.BIT_OBJECT | robot.BIT_FINGER,
        friction=[1.0, 0.02, 0.002],
        condim=4,
    )
    shape = asset.shape
    if shape == "cube":
        geoms = [dict(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02, 0.02, h])]
    elif shape == "cylinder":
        geoms = [dict(type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.021, h, 0])]
    elif shape == "cross":
        geoms = [
            dict(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.03, 0.01, h]),
            dict(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.01, 0.03, h]),
        ]
    elif shape == "bar":
        geoms = [dict(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.03, 0.013, h])]
    elif shape == "sphere":
        geoms = [dict(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.022, 0, 0])]
    elif shape == "disc":
        geoms = [dict(type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.03, 0.012, 0], pos=[0, 0, 0.012 - h])]
    elif shape in ("tri_prism", "hex_prism"):
        n, radius = (3, 0.026) if shape == "tri_prism" else (6, 0.024)
        mesh_name = f"{shape}_{label}"
        verts = []
        for z in (-h, h):
            for k in range(n):
                a = 2 * math.pi * k / n
                verts += [radius * math.cos(a), radius * math.sin(a), z]
        spec.add_mesh(name=mesh_name, uservert=verts)
        geoms = [dict(type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh_name)]
    else:  # pragma: no cover - assets are validated upstream
        raise ValueError(f"Unknown object shape {shape!r}; allowed: {', '.join(OBJECT_SHAPES)}")
    mass = OBJECT_MASS / len(geoms)
    for g in geoms:
        body.add_geom(**common, **g, mass=mass)


def add_receptacle_geoms(body, asset: Asset) -> None:
    """Static container: a floor and one box wall per polygon side."""
    shape = RECEPTACLE_SHAPES[asset.shape]
    common = dict(rgba=asset.rgba, contype=robot.BIT_TABLE, conaffinity=robot.BIT_OBJECT | robot.BIT_FINGER)
    verts = polygon_vertices(shape)
    inner = max(float(np.hypot(*v)) for v in verts)
    if len(verts) == 4:
        hx = max(abs(v[0]) for v in verts)
        hy = max(abs(v[1]) for v in verts)
        body.add_geom(
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[hx, hy, FLOOR_THICKNESS / 2],
            pos=[0, 0, FLOOR_THICKNESS / 2],
            **common,
        )
    else:
        apothem = min(shape.apothems)
        body.add_geom(
            type=mujoco.mjtGeom.mjGEOM_CYLINDER,
            size=[min(apothem + 0.003, inner), FLOOR_THICKNESS / 2, 0],
            pos=[0, 0, FLOOR_THICKNESS / 2],
            **common,
        )
    z = FLOOR_THICKNESS + shape.wall_height / 2
    for k, (angle_deg, apothem) in enumerate(zip(shape.normals_deg, shape.apothems)):
        v1, v2 = verts[k - 1], verts[k]  # the wall between the corners before and after this side
        length = float(np.hypot(*(v2 - v1)))
        a = math.radians(angle_deg)
        center = (apothem + WALL_THICKNESS / 2) * np.array([math.cos(a), math.sin(a)])
        body.add_geom(
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[WALL_THICKNESS / 2, length / 2 + WALL_THICKNESS / 2, shape.wall_height / 2],
            pos=[*center, z],
            quat=[math.cos(a / 2), 0, 0, math.sin(a / 2)],
            **common,
        )


def inside_receptacle(shape_name: str, local_xy: np.ndarray, margin: float = 0.004) -> bool:
    shape = RECEPTACLE_SHAPES[shape_name]
    for angle_deg, apothem in zip(shape.normals_deg, shape.apothems):
        a = math.radians(angle_deg)
        if local_xy[0] * math.cos(a) + local_xy[1] * math.sin(a) > apothem - margin:
            return False
    return True


def _quat_from_euler(rx: float, ry: float, rz: float) -> list[float]:
    q = np.zeros(4)
    mujoco.mju_euler2Quat(q, np.array([rx, ry, rz]), "xyz")
    return list(q)


def _add_lookat_camera(world, name, eye, target, fovy):
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    # MuJoCo cameras look along -z with +y up.
    mat = np.stack([right, up, -forward], axis=1)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, mat.flatten())
    world.add_camera(name=name, pos=list(eye), quat=list(quat), fovy=fovy)
