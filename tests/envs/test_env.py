import math

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import lerobot_condground  # noqa: F401
from lerobot_condground.envs.assets import COLORS, RECEPTACLE_SHAPES, WALL_THICKNESS
from lerobot_condground.envs.expert import JointDrift, ScriptedExpert, run_expert_episode
from lerobot_condground.envs.pickplace_env import PickPlaceEnv


def test_passes_gymnasiums_env_checker():
    env = gym.make(
        "gym_condground/PickPlaceFixedBin-v0",
        condition="object_color_1",
        observation_height=96,
        observation_width=128,
        wrist_camera=True,
        segmentation=True,
        prompts=True,
    )
    check_env(env.unwrapped, skip_render_check=False)
    assert env.spec.max_episode_steps == 300
    env.close()


def _episode(seed, **kwargs):
    env = PickPlaceEnv(
        task="PickPlaceRandomBin-v0",
        condition="full_mixed",
        observation_height=96,
        observation_width=128,
        **kwargs,
    )
    frames = []
    expert = ScriptedExpert()
    info = run_expert_episode(
        env, expert, seed, 300, on_step=lambda obs, a, p: frames.append(obs["pixels"]["top"])
    )
    env.close()
    return np.stack(frames), info


def test_same_seed_same_frames_and_outcome():
    a_frames, a_info = _episode(3)
    b_frames, b_info = _episode(3)
    c_frames, _ = _episode(4)
    assert a_frames.shape == b_frames.shape and np.array_equal(a_frames, b_frames)
    assert a_info == b_info and a_info["is_success"]
    assert a_frames.shape != c_frames.shape or not np.array_equal(a_frames, c_frames)


def test_drift_moves_the_arm_off_the_experts_path_and_back_before_the_grasp_while_the_labels_stay_its_own():
    """DART recovery data: the frames' actions are the expert's targets, the states are where the drifted arm
    went; the drift fades before the gripper closes, so the grasp still holds."""
    runs = {}
    for drift in (None, JointDrift(std=0.03, time_constant=0.5, fps=20, seed=7)):
        env = PickPlaceEnv(task="PickPlaceFixedBin-v0", condition="clean", obs_type="agent_pos")
        expert, frames = ScriptedExpert(), []
        info = run_expert_episode(
            env, expert, 7, 300, drift=drift,
            on_step=lambda obs, a, p: frames.append((obs["agent_pos"][:6].copy(), a.copy(), expert.phase)),  # noqa: B023
        )  # fmt: skip
        env.close()
        assert info["is_success"]
        runs[drift is None] = frames
    clean, drifted = runs[True], runs[False]
    assert [f[2] for f in clean] == [f[2] for f in drifted]
    assert all(np.array_equal(c[1], d[1]) for c, d in zip(clean, drifted, strict=True))
    off = {}
    for c, d in zip(clean, drifted, strict=True):
        off.setdefault(c[2], []).append(float(np.max(np.abs(c[0] - d[0]))))
    assert max(off["approach"]) > 0.03 and max(off["transport"]) > 0.03, off
    assert max(off["grasp"]) < 0.01, off["grasp"]


def test_reward_is_the_stage_index_and_stages_are_latched_in_order():
    env = PickPlaceEnv(task="PickPlaceFixedBin-v0", condition="receptacle_shape_1", obs_type="agent_pos")
    expert = ScriptedExpert()
    obs, info = env.reset(seed=5)
    expert.reset(env)
    assert info["stage"] == 0 and not info["is_success"]
    rewards, stages = [], []
    for _ in range(300):
        obs, reward, terminated, truncated, info = env.step(expert.act(obs))
        rewards.append(reward)
        stages.append(info["stage"])
        if terminated:
            break
    assert rewards == [float(s) for s in stages]
    assert np.all(np.diff(stages) >= 0) and set(stages) == {0, 1, 2, 3}
    assert info["is_success"] and info["grasped_first"] == 1 and info["grasped_first_match"] == "target"
    assert info["target_location"] == "target_receptacle"


def test_holding_a_competitor_is_not_a_pick_and_is_reported():
    """Steer the expert to a color-matched competitor: the grasp is recorded, the pick is not."""
    env = PickPlaceEnv(task="PickPlaceRandomBin-v0", condition="object_color_1", obs_type="agent_pos")
    expert = ScriptedExpert()
    obs, _ = env.reset(seed=2)
    expert.reset(env)
    competitor = next(e for e in env.layout.entities if e.match == "color")
    real_pose = env.entity_pose
    env.entity_pose = lambda label: real_pose(competitor.label if label == 1 else label)
    expert.reset(env)
    for _ in range(60):
        obs, reward, terminated, _, info = env.step(expert.act(obs))
        if expert.phase == "transport":
            break
    assert info["grasped_first"] == competitor.label and info["grasped_first_match"] == "color"
    assert info["grasped_competitor"] == competitor.label
    assert info["stage"] == 0 and not info["pick"]


@pytest.mark.parametrize("seed", [0, 1])
def test_a_receptacle_wall_between_the_fingers_is_no_grasp(seed):
    """Steer the expert's grasp onto a competitor receptacle's wall, fingers on either side of it: it held
    nothing (counting it once reported a competitor grasped and placed in its own receptacle)."""
    env = PickPlaceEnv(task="PickPlaceFixedBin-v0", condition="receptacle_shape_1", obs_type="agent_pos")
    obs, _ = env.reset(seed=seed)
    rec = next(e for e in env.layout.entities if e.asset.role == "receptacle" and e.match == "shape")
    shape = RECEPTACLE_SHAPES[rec.asset.shape]
    normal = math.radians(shape.normals_deg[0]) + rec.yaw
    reach = shape.apothems[0] + WALL_THICKNESS / 2
    wall = np.array([rec.xy[0] + reach * math.cos(normal), rec.xy[1] + reach * math.sin(normal), 0.02])
    real_pose = env.entity_pose
    env.entity_pose = (
        lambda label: (wall.copy(), np.array([1.0, 0, 0, 0])) if label == 1 else real_pose(label)
    )
    expert = ScriptedExpert()
    expert._grasp_yaw = lambda _: normal + math.pi / 2  # the fingers close along the wall's normal
    expert.reset(env)
    finger_sides = set()
    for _ in range(80):
        obs, _, _, _, info = env.step(expert.act(obs))
        g1, g2 = env.data.contact.geom1[: env.data.ncon], env.data.contact.geom2[: env.data.ncon]
        for finger, other in ((g1, g2), (g2, g1)):
            sides = env.tracker.finger_of_geom[finger]
            finger_sides |= set(sides[(env.tracker.geom_label[other] == rec.label) & (sides > 0)].tolist())
        if expert.phase == "transport":
            break
    assert finger_sides == {1, 2}, "both fingers should have touched the wall"
    assert info["grasped_first"] == 0 and info["grasped_competitor"] == 0
    assert info["competitor_location"] == "none" and info["stage"] == 0
    env.close()


def test_segmentation_masks_cover_the_entities_they_name():
    env = PickPlaceEnv(task="PickPlaceRandomBin-v0", condition="full_mixed", segmentation=True, prompts=True)
    obs, _ = env.reset(seed=1)
    rgb, seg = obs["pixels"]["top"].astype(float) / 255, obs["segmentation"]
    for entity in env.layout.entities:
        mask = seg == entity.label
        assert mask.sum() > 30, entity
        # Shading varies, hue does not: the masked pixels are nearest to the entity's own color.
        mean = rgb[mask].mean(axis=0)
        nearest = min(
            COLORS, key=lambda c: np.linalg.norm(mean / mean.max() - np.array(COLORS[c]) / max(COLORS[c]))
        )
        assert nearest == entity.asset.color, (entity, mean)
    for key, label in (("prompt_object", 1), ("prompt_receptacle", 2)):
        crop = obs[key].astype(float) / 255
        color = np.array(COLORS[env.layout.entities[label - 1].asset.color])
        centre = crop[24:40, 24:40].reshape(-1, 3).mean(axis=0)
        assert np.argmax(centre) == np.argmax(color) or np.allclose(color[:2], color[:2].max(), atol=0.1)
    env.close()


@pytest.mark.parametrize(
    "kwargs, fragment",
    [
        (dict(task="PickPlace-v9"), "Unknown task 'PickPlace-v9'"),
        (dict(condition="mixed"), "Unknown condition 'mixed'"),
        (dict(condition="object_shape=5"), "object_shape=5 is out of range"),
        (dict(observation_height=720, observation_width=1280), "Image height 720 cannot be rendered"),
        (dict(observation_width=32), "Image width 32 cannot be rendered"),
        (dict(fps=33), "Control rate fps=33 is not allowed"),
        (dict(obs_type="states"), "Unknown obs_type 'states'"),
        (dict(servo="fast"), "servo='fast' is not allowed; allowed: interpolated, direct"),
        (
            dict(competitor_pool="train"),
            "competitor_pool='train' is not allowed; allowed: eval, augmentation",
        ),
    ],
)
def test_bad_construction_is_refused_with_the_value_named(kwargs, fragment):
    with pytest.raises(ValueError, match="allowed") as err:
        PickPlaceEnv(**kwargs)
    assert fragment in str(err.value)


@pytest.mark.parametrize("action", [np.zeros(6), np.full(7, np.nan), np.zeros((2, 7))])
def test_bad_actions_are_refused(action):
    env = PickPlaceEnv(obs_type="agent_pos")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="Action must be 7 finite numbers"):
        env.step(action)


def test_task_description_names_the_targets():
    env = PickPlaceEnv(task="PickPlaceRandomBin-v0", counterbalanced=True, obs_type="agent_pos")
    descriptions = set()
    for seed in range(8):
        env.reset(seed=seed)
        t = env.layout
        assert (
            env.task_description
            == f"Pick the {t.target_object.asset} and place it in the {t.target_receptacle.asset}."
        )
        descriptions.add(env.task_description)
    assert len(descriptions) > 1


def test_largest_resolution_and_wrist_camera_render():
    env = PickPlaceEnv(observation_height=480, observation_width=640, wrist_camera=True, segmentation=True)
    obs, _ = env.reset(seed=0)
    assert obs["pixels"]["top"].shape == obs["pixels"]["wrist"].shape == (480, 640, 3)
    assert obs["segmentation"].shape == (480, 640) and (obs["segmentation"] == 1).sum() > 100
    assert not np.array_equal(obs["pixels"]["top"], obs["pixels"]["wrist"])
    env.close()


def test_a_diverging_simulation_truncates_the_episode_with_a_flag():
    env = PickPlaceEnv(obs_type="agent_pos")
    _, info = env.reset(seed=0)
    assert info["physics_unstable"] is False
    _, _, terminated, truncated, info = env.step(np.concatenate([env.joint_positions(), [0.0]]))
    assert not truncated and not info["physics_unstable"]
    env.data.qvel[-1] = 1e30  # what a blown-up solver leaves behind
    _, _, terminated, truncated, info = env.step(np.concatenate([env.joint_positions(), [0.0]]))
    assert truncated and info["physics_unstable"] and not terminated


def test_a_jump_of_the_joint_targets_is_taken_at_the_ur3e_rated_speed_unless_servo_is_direct():
    """Between two action chunks a policy's target can jump; the UR3e's servo stream (and the twin) takes a
    jump no faster than the arm's rated joint speeds, while set at once the servos whip the arm round."""
    home = np.concatenate([PickPlaceEnv(obs_type="agent_pos").reset(seed=0)[0]["agent_pos"][:6], [0.0]])
    jump = home + [0.6, 0, 0, 0.8, 0, 0, 0]  # base and wrist 1
    rated = np.array([math.pi] * 3 + [2 * math.pi] * 3)
    fastest = {}
    for servo in ("interpolated", "direct"):
        env = PickPlaceEnv(obs_type="agent_pos", servo=servo)
        env.reset(seed=0)
        speeds = []
        for _ in range(8):
            before = env.joint_positions()
            env.step(jump)
            speeds.append(np.abs(env.joint_positions() - before) * env.fps)  # mean speed over the period
        fastest[servo] = np.max(speeds, axis=0)
        np.testing.assert_allclose(env.joint_positions(), jump[:6], atol=0.02)  # both get there
    # The arm lags its set point by a few milliseconds; a tenth of the limit is room for the catching up.
    assert np.all(fastest["interpolated"] <= 1.1 * rated), fastest
    assert fastest["direct"][0] > 1.5 * rated[0], fastest  # what servo=direct measured before


def test_a_target_within_the_rated_speeds_is_the_set_point_at_the_end_of_the_period():
    env = PickPlaceEnv(obs_type="agent_pos")
    env.reset(seed=0)
    target = np.concatenate([env.joint_positions() + [0.05, -0.05, 0.05, 0.1, -0.1, 0.1], [0.0]])
    env.step(target)
    np.testing.assert_array_equal(env.data.ctrl[:6], target[:6])
