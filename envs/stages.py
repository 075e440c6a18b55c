"""Stage events of one episode, read off contacts and poses and latched once reached.

pick:  the target object held between both fingers (a held competitor is not a pick; a receptacle's wall
       between the fingers holds nothing: receptacles are fixed, and counting one would report a competitor
       object grasped and placed in its own receptacle);
lift:  the held target's bottom above LIFT_HEIGHT;
place: after pick and lift, the target at rest inside the target receptacle with no finger on it.
The reward of a step is the stage index reached so far (0..3).
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from .assets import FLOOR_THICKNESS, OBJECT_HEIGHT, RECEPTACLE_SHAPES
from .layout import Layout
from .scene import entity_body_name, inside_receptacle

LIFT_HEIGHT = 0.04
REST_SPEED = 0.03  # m/s
STAGES = ("none", "pick", "lift", "place")
LOCATIONS = ("target_receptacle", "competitor_receptacle", "elsewhere")


class StageTracker:
    def __init__(self, model: mujoco.MjModel, layout: Layout):
        self.model = model
        self.layout = layout
        self.geom_label = np.zeros(model.ngeom, dtype=np.int32)
        for e in layout.entities:
            self.geom_label[
                model.body_geomadr[model.body(entity_body_name(e.label)).id]
                + np.arange(model.body_geomnum[model.body(entity_body_name(e.label)).id])
            ] = e.label
        self.finger_of_geom = np.zeros(model.ngeom, dtype=np.int8)  # 1 left, 2 right
        for side, code in (("left_finger", 1), ("right_finger", 2)):
            bid = model.body(side).id
            self.finger_of_geom[
                model.body_geomadr[bid] : model.body_geomadr[bid] + model.body_geomnum[bid]
            ] = code
        self.body_of_label = {e.label: model.body(entity_body_name(e.label)).id for e in layout.entities}
        self.receptacles = [e for e in layout.entities if e.asset.role == "receptacle"]
        self.objects = {e.label for e in layout.entities if e.asset.role == "object"}
        self.reset()

    def reset(self) -> None:
        self.pick = self.lift = self.place = False
        self.grasped_first = 0  # label of the first object held between both fingers, 0 = none yet
        self.grasped_competitor = 0  # label of the first competitor object held, 0 = none
        self.held = 0

    @property
    def stage(self) -> int:
        return 3 if self.place else 2 if self.lift else 1 if self.pick else 0

    def update(self, data: mujoco.MjData) -> None:
        g1, g2 = data.contact.geom1[: data.ncon], data.contact.geom2[: data.ncon]
        touching = {}
        for side in (1, 2):
            labels = np.concatenate(
                [
                    self.geom_label[g2][self.finger_of_geom[g1] == side],
                    self.geom_label[g1][self.finger_of_geom[g2] == side],
                ]
            )
            touching[side] = set(labels[labels > 0].tolist())
        held = touching[1] & touching[2] & self.objects
        self.held = min(held) if held else 0
        target_touched = 1 in touching[1] or 1 in touching[2]
        if self.held:
            if not self.grasped_first:
                self.grasped_first = self.held
            if self.held >= 3 and not self.grasped_competitor:
                self.grasped_competitor = self.held
        if self.held == 1:
            self.pick = True
            if self.pick and self.bottom_height(data, 1) > LIFT_HEIGHT:
                self.lift = True
        if self.pick and self.lift and not self.place and not target_touched:
            speed = float(np.linalg.norm(data.cvel[self.body_of_label[1]][3:]))
            if speed < REST_SPEED and self.location(data, 1) == "target_receptacle":
                self.place = True

    def bottom_height(self, data: mujoco.MjData, label: int) -> float:
        return float(data.xpos[self.body_of_label[label]][2]) - OBJECT_HEIGHT / 2

    def location(self, data: mujoco.MjData, label: int) -> str:
        """Where an object stands now: inside the target receptacle, a competitor's, or elsewhere."""
        pos = data.xpos[self.body_of_label[label]]
        for rec in self.receptacles:
            shape = RECEPTACLE_SHAPES[rec.asset.shape]
            rel = pos[:2] - np.array(rec.xy)
            c, s = math.cos(-rec.yaw), math.sin(-rec.yaw)
            local = np.array([c * rel[0] - s * rel[1], s * rel[0] + c * rel[1]])
            if pos[2] < FLOOR_THICKNESS + shape.wall_height + OBJECT_HEIGHT / 2 and inside_receptacle(
                rec.asset.shape, local
            ):
                return "target_receptacle" if rec.is_target else "competitor_receptacle"
        return "elsewhere"

    def info(self, data: mujoco.MjData) -> dict:
        return {
            "is_success": self.place,
            "stage": self.stage,
            "pick": self.pick,
            "lift": self.lift,
            "place": self.place,
            "grasped_first": self.grasped_first,
            "grasped_first_match": self._match(self.grasped_first),
            "target_location": self.location(data, 1),
            "grasped_competitor": self.grasped_competitor,
            "competitor_location": self.location(data, self.grasped_competitor)
            if self.grasped_competitor
            else "none",
        }

    def _match(self, label: int) -> str:
        if not label:
            return "none"
        entity = self.layout.entities[label - 1]
        return entity.match
