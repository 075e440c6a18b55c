import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from lerobot_condground.core.conditions import FIELD_NAMES, TASKS, ConditionSpec
from lerobot_condground.envs import assets, layout, robot
from lerobot_condground.envs.robot import InverseKinematics, tool_rotation


def test_evaluation_and_augmentation_pools_are_disjoint():
    ev, aug = assets.pool_assets("eval"), assets.pool_assets("augmentation")
    assert ev and aug and not (ev & aug)
    assert not set(assets.EVAL_COLORS) & set(assets.AUGMENTATION_COLORS)
    for role in assets.ROLES:
        assert not set(assets.pool_shapes(role, "eval")) & set(assets.pool_shapes(role, "augmentation"))
    with pytest.raises(ValueError, match="Unknown asset pool 'train'"):
        assets.pool_assets("train")


specs = st.builds(ConditionSpec, **{f: st.integers(0, 1) for f in FIELD_NAMES})


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(task=st.sampled_from(TASKS), spec=specs, counterbalanced=st.booleans(), seed=st.integers(0, 2**31 - 2))
def test_layouts_never_overlap_stay_in_reach_and_match_their_class(task, spec, counterbalanced, seed):
    lay = layout.sample_layout(task, spec, counterbalanced, seed)
    assert len(lay.entities) == 2 + spec.num_competitors
    eval_assets = assets.pool_assets("eval")
    for i, a in enumerate(lay.entities):
        r, angle = math.hypot(*a.xy), math.atan2(a.xy[1], a.xy[0])
        assert layout.R_MIN - 1e-9 <= r <= layout.R_MAX + 1e-9 and abs(angle) <= layout.ANGLE_MAX + 1e-9
        assert a.asset in eval_assets
        for b in lay.entities[i + 1 :]:
            assert math.dist(a.xy, b.xy) >= a.clearance + b.clearance + layout.GAP - 1e-9
    targets = {"object": lay.target_object.asset, "receptacle": lay.target_receptacle.asset}
    for e in lay.entities[2:]:
        t = targets[e.asset.role]
        same_color, same_shape = e.asset.color == t.color, e.asset.shape == t.shape
        assert (same_color, same_shape) == {
            "color": (True, False),
            "shape": (False, True),
            "neither": (False, False),
        }[e.match]
    if task == "PickPlaceFixedBin-v0":
        assert lay.target_receptacle.xy == pytest.approx(layout.FIXED_RECEPTACLE_XY)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(task=st.sampled_from(TASKS), counterbalanced=st.booleans(), seed=st.integers(0, 2**31 - 2))
def test_augmentation_pool_competitors_match_as_pastes_and_are_never_evaluation_assets(
    task, counterbalanced, seed
):
    """Recording among rendered competitors (`--env.competitor_pool=augmentation`) must never show the policy
    an asset an evaluation scene can hold; the targets and their poses stay those of the evaluation pool."""
    spec = ConditionSpec.parse("full_mixed")
    lay = layout.sample_layout(task, spec, counterbalanced, seed, "augmentation")
    evaluation = layout.sample_layout(task, spec, counterbalanced, seed)
    assert lay.entities[:2] == evaluation.entities[:2]
    eval_assets, aug_colors = assets.pool_assets("eval"), set(assets.AUGMENTATION_COLORS)
    for e in lay.entities[2:]:
        t = lay.entities[0 if e.asset.role == "object" else 1].asset
        aug_shape = e.asset.shape in assets.pool_shapes(e.asset.role, "augmentation")
        assert e.asset not in eval_assets
        assert (
            e.asset.color == t.color,
            e.asset.shape == t.shape,
            aug_shape,
            e.asset.color in aug_colors,
        ) == {
            "color": (True, False, True, False),
            "shape": (False, True, False, True),
            "neither": (False, False, True, True),
        }[e.match]


def test_competitor_pools_vary_and_a_bad_pool_is_refused():
    shapes = {
        e.asset.shape
        for s in range(20)
        for e in layout.sample_layout(
            "PickPlaceFixedBin-v0", ConditionSpec.parse("object_neither_1"), False, s, "augmentation"
        ).entities[2:]
    }
    assert len(shapes) > 1
    with pytest.raises(
        ValueError, match="competitor_pool='train' is not allowed; allowed: eval, augmentation"
    ):
        layout.sample_layout("PickPlaceFixedBin-v0", ConditionSpec(), False, 0, "train")


def test_same_seed_same_layout_and_paired_targets_across_conditions():
    a = layout.sample_layout("PickPlaceRandomBin-v0", ConditionSpec.parse("full_mixed"), True, 7)
    assert a == layout.sample_layout("PickPlaceRandomBin-v0", ConditionSpec.parse("full_mixed"), True, 7)
    for task in TASKS:
        clean = layout.sample_layout(task, ConditionSpec(), False, 11)
        for name in ("object_color_3", "receptacle_shape_2", "full_mixed"):
            other = layout.sample_layout(task, ConditionSpec.parse(name), False, 11)
            assert other.entities[:2] == clean.entities[:2]


def test_counterbalanced_mode_permutes_targets_over_the_pool():
    seen = {
        layout.sample_layout("PickPlaceRandomBin-v0", ConditionSpec(), True, s).target_object.asset
        for s in range(60)
    }
    assert {a.color for a in seen} == set(assets.EVAL_COLORS)
    assert {a.shape for a in seen} == set(assets.EVAL_OBJECT_SHAPES)


def test_a_layout_that_cannot_fit_is_refused_with_the_condition_named():
    crowded = ConditionSpec(**dict.fromkeys(FIELD_NAMES, 3))
    with pytest.raises(
        layout.LayoutError, match=r"does not fit on the table: 20 entities \(18 competitors\)"
    ):
        layout.check_fits("PickPlaceRandomBin-v0", crowded, False)


def test_every_point_of_the_workspace_is_reachable_top_down():
    """The sampler's region is reachable with the tool pointing down, at grasp and carry heights."""
    import mujoco

    lay = layout.sample_layout("PickPlaceRandomBin-v0", ConditionSpec(), False, 0)
    from lerobot_condground.envs.scene import build_model

    model = build_model(lay)
    ik = InverseKinematics(model)
    for r in np.linspace(layout.R_MIN, layout.R_MAX, 4):
        for angle in np.linspace(-layout.ANGLE_MAX, layout.ANGLE_MAX, 7):
            for z in (0.02, 0.13):
                goal = np.array([r * math.cos(angle), r * math.sin(angle), z])
                q0 = robot.HOME_QPOS.copy()
                q0[0] = angle - math.asin(0.131 / r)
                q = ik.solve(q0, goal, angle, iters=100)
                ik.data.qpos[ik.qadr] = q
                mujoco.mj_kinematics(model, ik.data)
                assert np.linalg.norm(ik.data.site_xpos[ik.site] - goal) < 2e-3, (r, angle, z)
                assert np.allclose(ik.data.site_xmat[ik.site].reshape(3, 3), tool_rotation(angle), atol=2e-2)
