"""The UR3e-like arm and its parallel-jaw gripper, built with MjSpec from UR3e's published DH table.

Primitive geoms only: software rendering pays per triangle. The joint and gripper layout matches the
real UR3e robot of this project, so a policy's features line up between simulation and hardware.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from lerobot_condground.core.ur3e import (  # noqa: F401  (the twin's names are the hardware's)
    FLANGE_TO_TCP,
    GRIPPER_NAME,
    GRIPPER_STROKE,
    HOME_QPOS,
    JOINT_NAMES,
    MOTOR_NAMES,
    UR3E_DH_A,
    UR3E_DH_ALPHA,
    UR3E_DH_D,
)

# UR3e limits: +-360 deg on every joint, elbow restricted to +-180 deg by self-collision.
JOINT_RANGE = np.array([[-2 * math.pi, 2 * math.pi]] * 6)
JOINT_RANGE[2] = (-math.pi, math.pi)
# UR3e rated joint torques (Nm): the servos cannot exceed them, so a wild target (a random or broken
# policy) moves the arm at a bounded acceleration instead of throwing the solver off.
JOINT_TORQUE = (54.0, 54.0, 28.0, 12.0, 12.0, 12.0)

FINGER_TRAVEL = GRIPPER_STROKE / 2  # each finger travels half the stroke
GRIPPER_FORCE = 25.0  # N, clamps like a force-limited adaptive gripper

ARM_GROUP, GRIPPER_GROUP = 1, 2  # geom groups, used to filter rendering and contacts
# contype/conaffinity bits. Arm links collide with nothing (stiff servos driving a link into a block make
# the solver blow up, and the expert never needs it); the gripper touches objects, receptacles and table.
BIT_TABLE, BIT_OBJECT, BIT_FINGER = 1, 2, 8


def _rx(alpha: float) -> list[float]:
    return [math.cos(alpha / 2), math.sin(alpha / 2), 0.0, 0.0]


def add_ur3e(spec: mujoco.MjSpec, base_pos=(0.0, 0.0, 0.0)) -> None:
    """Adds the arm, its position servos and the gripper to `spec`.

    The base is turned by 180 deg about z so that the zero pose (which points along -x in UR's
    convention) reaches over the table on +x.
    """
    spec.compiler.degree = False
    link_rgba = [0.75, 0.78, 0.82, 1.0]
    joint_rgba = [0.2, 0.35, 0.6, 1.0]
    radii = (0.045, 0.04, 0.035, 0.03, 0.03, 0.03)

    base = spec.worldbody.add_body(name="ur3e_base", pos=list(base_pos), quat=[0.0, 0.0, 0.0, 1.0])
    base.add_geom(
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[0.06, 0.04, 0],
        pos=[0, 0, 0.04],
        rgba=joint_rgba,
        contype=0,
        conaffinity=0,
        group=ARM_GROUP,
    )
    parent = base
    for i in range(6):
        if i == 0:
            pos, quat = [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
        else:
            pos = [UR3E_DH_A[i - 1], 0.0, UR3E_DH_D[i - 1]]
            quat = _rx(UR3E_DH_ALPHA[i - 1])
        body = parent.add_body(name=f"link{i + 1}", pos=pos, quat=quat, gravcomp=1.0)
        jnt = body.add_joint(
            name=JOINT_NAMES[i],
            type=mujoco.mjtJoint.mjJNT_HINGE,
            axis=[0, 0, 1],
            range=list(JOINT_RANGE[i]),
            armature=0.1,
            damping=2.0,
        )
        jnt.limited = mujoco.mjtLimited.mjLIMITED_TRUE
        r = radii[i]
        # Joint housing along the joint axis, then the link to the next DH frame (z by d, then x by a).
        body.add_geom(
            type=mujoco.mjtGeom.mjGEOM_CYLINDER,
            size=[r * 1.15, r * 1.1, 0],
            rgba=joint_rgba,
            contype=0,
            conaffinity=0,
            group=ARM_GROUP,
            mass=0.3,
        )
        d, a = UR3E_DH_D[i], UR3E_DH_A[i]
        if abs(d) > 1e-6 and i < 5:
            body.add_geom(
                type=mujoco.mjtGeom.mjGEOM_CAPSULE,
                fromto=[0, 0, 0, 0, 0, d],
                size=[r, 0, 0],
                rgba=link_rgba,
                contype=0,
                conaffinity=0,
                group=ARM_GROUP,
                mass=0.5,
            )
        if abs(a) > 1e-6:
            body.add_geom(
                type=mujoco.mjtGeom.mjGEOM_CAPSULE,
                fromto=[0, 0, d, a, 0, d],
                size=[r, 0, 0],
                rgba=link_rgba,
                contype=0,
                conaffinity=0,
                group=ARM_GROUP,
                mass=1.0,
            )
        act = spec.add_actuator(
            name=f"{JOINT_NAMES[i]}_servo", target=JOINT_NAMES[i], trntype=mujoco.mjtTrn.mjTRN_JOINT
        )
        kp = 3000.0 if i < 3 else 800.0
        act.set_to_position(kp=kp, dampratio=1.0)
        act.forcerange = [-JOINT_TORQUE[i], JOINT_TORQUE[i]]
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.ctrlrange = list(JOINT_RANGE[i])
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        parent = body
    flange = parent.add_body(name="flange", pos=[0.0, 0.0, UR3E_DH_D[5]], gravcomp=1.0)
    _add_gripper(spec, flange)


def _add_gripper(spec: mujoco.MjSpec, flange) -> None:
    dark = [0.15, 0.15, 0.17, 1.0]
    pad_rgba = [0.3, 0.3, 0.32, 1.0]
    flange.add_geom(
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[0.035, 0.03, 0],
        pos=[0, 0, 0.03],
        rgba=dark,
        contype=BIT_FINGER,
        conaffinity=BIT_OBJECT | BIT_TABLE,
        group=GRIPPER_GROUP,
        mass=0.4,
    )
    flange.add_geom(
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[0.055, 0.02, 0.015],
        pos=[0, 0, 0.075],
        rgba=dark,
        contype=BIT_FINGER,
        conaffinity=BIT_OBJECT | BIT_TABLE,
        group=GRIPPER_GROUP,
        mass=0.3,
    )
    flange.add_site(name="tcp", pos=[0, 0, FLANGE_TO_TCP], size=[0.005, 0, 0])
    for side, sign in (("left", 1.0), ("right", -1.0)):
        # A finger at q=0 stands fully open; q=FINGER_TRAVEL closes it onto the tool axis.
        finger = flange.add_body(name=f"{side}_finger", pos=[0, 0, 0.09], gravcomp=1.0)
        finger.add_joint(
            name=f"{side}_finger",
            type=mujoco.mjtJoint.mjJNT_SLIDE,
            axis=[-sign, 0, 0],
            range=[0.0, FINGER_TRAVEL],
            armature=0.01,
            damping=5.0,
        )
        x_open = sign * (FINGER_TRAVEL + 0.008)
        finger.add_geom(
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[0.006, 0.012, 0.032],
            pos=[x_open + sign * 0.004, 0, 0.035],
            rgba=dark,
            contype=BIT_FINGER,
            conaffinity=BIT_OBJECT | BIT_TABLE,
            group=GRIPPER_GROUP,
            mass=0.05,
        )
        finger.add_geom(
            name=f"{side}_pad",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[0.004, 0.011, 0.02],
            pos=[x_open - sign * 0.006, 0, FLANGE_TO_TCP - 0.09],
            rgba=pad_rgba,
            contype=BIT_FINGER,
            conaffinity=BIT_OBJECT | BIT_TABLE,
            group=GRIPPER_GROUP,
            friction=[1.5, 0.02, 0.002],
            condim=4,
            mass=0.02,
        )
    eq = spec.add_equality(type=mujoco.mjtEq.mjEQ_JOINT, name1="right_finger", name2="left_finger")
    eq.data[:5] = [0, 1, 0, 0, 0]
    act = spec.add_actuator(name="gripper_servo", target="left_finger", trntype=mujoco.mjtTrn.mjTRN_JOINT)
    act.set_to_position(kp=2000.0, dampratio=1.0)
    act.ctrlrange = [0.0, FINGER_TRAVEL]
    act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
    act.forcerange = [-GRIPPER_FORCE, GRIPPER_FORCE]
    act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE


def tool_rotation(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.diag([1.0, -1.0, -1.0])


class InverseKinematics:
    """Damped least squares on the tool-center site, position and orientation."""

    def __init__(self, model: mujoco.MjModel):
        self.model = model
        self.data = mujoco.MjData(model)
        self.site = model.site("tcp").id
        self.qadr = np.array([model.joint(n).qposadr[0] for n in JOINT_NAMES])
        self.dofadr = np.array([model.joint(n).dofadr[0] for n in JOINT_NAMES])
        self._jp = np.zeros((3, model.nv))
        self._jr = np.zeros((3, model.nv))

    def solve(self, q0: np.ndarray, pos: np.ndarray, yaw: float, iters: int = 30) -> np.ndarray:
        q = q0.copy()
        target_rot = tool_rotation(yaw)
        for _ in range(iters):
            self.data.qpos[self.qadr] = q
            mujoco.mj_kinematics(self.model, self.data)
            mujoco.mj_comPos(self.model, self.data)
            err_p = pos - self.data.site_xpos[self.site]
            rot = self.data.site_xmat[self.site].reshape(3, 3)
            err_r = 0.5 * sum(np.cross(rot[:, k], target_rot[:, k]) for k in range(3))
            if np.linalg.norm(err_p) < 1e-4 and np.linalg.norm(err_r) < 1e-3:
                break
            mujoco.mj_jacSite(self.model, self.data, self._jp, self._jr, self.site)
            jac = np.vstack([self._jp[:, self.dofadr], self._jr[:, self.dofadr]])
            err = np.concatenate([err_p, err_r])
            q = q + jac.T @ np.linalg.solve(jac @ jac.T + 1e-4 * np.eye(6), err)
            q = np.clip(q, JOINT_RANGE[:, 0], JOINT_RANGE[:, 1])
        return q

    def forward(self, q: np.ndarray) -> tuple[np.ndarray, float]:
        """Tool-center position and yaw at joint positions `q`."""
        self.data.qpos[self.qadr] = q
        mujoco.mj_kinematics(self.model, self.data)
        rot = self.data.site_xmat[self.site].reshape(3, 3)
        return self.data.site_xpos[self.site].copy(), math.atan2(rot[1, 0], rot[0, 0])

    def solve_from(self, q0: np.ndarray, pos: np.ndarray, yaw: float, steps: int = 20) -> np.ndarray:
        """Joint positions for a distant tool pose, reached from `q0` through `steps` intermediate poses on
        the straight line: one far jump lets damped least squares settle in another arm configuration."""
        start, start_yaw = self.forward(q0)
        dyaw = (yaw - start_yaw + math.pi) % (2 * math.pi) - math.pi
        q = q0.copy()
        for k in range(1, steps + 1):
            s = k / steps
            q = self.solve(q, start + s * (np.asarray(pos) - start), start_yaw + s * dyaw)
        return self.solve(q, np.asarray(pos), yaw, iters=100)
