"""Sprites of the augmentation-pool shapes, rendered once with MuJoCo from the scene camera.

Each sprite is (shading, alpha): the shape rendered in a mid-gray albedo divided by that albedo, so a
sprite tinted with a color looks like the shape rendered in that color (gray leaves headroom: a white
albedo would clip highlights at 1 and flatten the shading). Alpha comes from segmentation rendering.
MuJoCo is imported here only, so a step restored from a checkpoint never needs it.
"""

from __future__ import annotations

import numpy as np
import torch

from lerobot_condground.envs.assets import AUGMENTATION_OBJECT_SHAPES, AUGMENTATION_RECEPTACLE_SHAPES

# Bank order: object shapes, then receptacle shapes (the step indexes sprites by role this way).
SPRITE_SHAPES = (
    *(("object", s) for s in AUGMENTATION_OBJECT_SHAPES),
    *(("receptacle", s) for s in AUGMENTATION_RECEPTACLE_SHAPES),
)
# Rendered at the largest camera resolution and scaled down to the frames: pixel size depends on the
# image height only (MuJoCo's fovy is vertical), so one bank serves every resolution.
BANK_HEIGHT, BANK_WIDTH = 480, 640
# The camera looks at this point of the table, so a sprite rendered here is centered and of typical size.
RENDER_XY = (0.17, 0.0)
ALBEDO = 0.5
PAD = 2


def render_sprite_bank() -> torch.Tensor:
    """(len(SPRITE_SHAPES), 2, S, S) float32: shading and alpha, each shape centered on a common square."""
    import mujoco

    from lerobot_condground.envs import robot, scene
    from lerobot_condground.envs.assets import Asset
    from lerobot_condground.envs.layout import Entity, Layout

    # One model holds every shape; all but the one being rendered wait off camera.
    parked = tuple(
        Entity(k + 1, Asset(role, shape, "orange"), "neither", (-3.0, 0.5 * k), 0.0)
        for k, (role, shape) in enumerate(SPRITE_SHAPES)
    )
    model = scene.build_model(Layout("sprites", parked))
    model.geom_rgba[:, :3] = ALBEDO
    data = mujoco.MjData(model)
    option = mujoco.MjvOption()
    option.geomgroup[robot.ARM_GROUP] = 0
    option.geomgroup[robot.GRIPPER_GROUP] = 0
    renderer = mujoco.Renderer(model, BANK_HEIGHT, BANK_WIDTH)
    crops = []
    try:
        for k, entity in enumerate(parked):
            posed = tuple(
                Entity(e.label, e.asset, e.match, RENDER_XY if j == k else e.xy, 0.0)
                for j, e in enumerate(parked)
            )
            scene.apply_layout(model, data, Layout("sprites", posed))
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera="top", scene_option=option)
            rgb = renderer.render().astype(np.float32) / 255.0
            renderer.enable_segmentation_rendering()
            renderer.update_scene(data, camera="top", scene_option=option)
            seg = renderer.render()
            renderer.disable_segmentation_rendering()
            ids = seg[..., 0]
            is_geom = (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)) & (ids >= 0)
            body = model.body(scene.entity_body_name(entity.label)).id
            alpha = is_geom & (model.geom_bodyid[np.clip(ids, 0, None)] == body)
            ys, xs = np.nonzero(alpha)
            box = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
            shading = rgb[box].mean(-1) / ALBEDO
            crops.append(np.stack([shading * alpha[box], alpha[box].astype(np.float32)]))
    finally:
        renderer.close()
    side = max(max(c.shape[1:]) for c in crops) + 2 * PAD
    bank = np.zeros((len(crops), 2, side, side), dtype=np.float32)
    for k, crop in enumerate(crops):
        h, w = crop.shape[1:]
        y0, x0 = (side - h) // 2, (side - w) // 2
        bank[k, :, y0 : y0 + h, x0 : x0 + w] = crop
    return torch.from_numpy(bank)
