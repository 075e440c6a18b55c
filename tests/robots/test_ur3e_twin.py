"""The `ur3e` robot on its MuJoCo twin: stock lerobot-record / lerobot-rollout end to end, and the safety
layer (limits, stall watchdog, disconnect on exceptions, bad input) through the same robot class that
drives the hardware."""

import json
import os
import pty
import subprocess
import sys
import time

import numpy as np
import pytest
from lerobot.cameras.opencv import OpenCVCameraConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.utils.feature_utils import hw_to_dataset_features

from helpers import make_checkpoint, run_cli
from lerobot_condground.cameras import ur3e_twin
from lerobot_condground.cameras.config_ur3e_twin import UR3eTwinCameraConfig
from lerobot_condground.core.configs import ConfigError
from lerobot_condground.core.labels import OBS_PHASE, OBS_PROMPT_OBJECT, OBS_SEGMENTATION, decode_png
from lerobot_condground.envs.pickplace_env import PickPlaceEnv
from lerobot_condground.envs.robot import HOME_QPOS, MOTOR_NAMES
from lerobot_condground.labelling.prompts import click_on
from lerobot_condground.labelling.segmenters import save_random_sam2
from lerobot_condground.robots import kinematics
from lerobot_condground.robots.config_ur3e import UR3eConfig, UR3ePromptsConfig, UR3eSimConfig
from lerobot_condground.robots.ur3e import UR3e
from lerobot_condground.teleoperators.config_ur3e_teleops import UR3eExpertConfig
from lerobot_condground.teleoperators.ur3e_teleops import UR3eExpert

TWIN_CAMERA = "--robot.cameras={top: {type: ur3e_twin, width: 128, height: 96, fps: 20}}"
RECORD_FLAGS = ["--dataset.push_to_hub=false", "--play_sounds=false", "--dataset.fps=20"]


def twin(realtime=False, condition="clean", **kwargs) -> UR3e:
    cameras = {"top": UR3eTwinCameraConfig(width=128, height=96, fps=20)}
    return UR3e(
        UR3eConfig(
            backend="sim",
            cameras=cameras,
            sim=UR3eSimConfig(realtime=realtime, condition=condition),
            **kwargs,
        )
    )


def action(q, gripper=0.0) -> dict:
    return dict(zip(MOTOR_NAMES, [*map(float, q), float(gripper)], strict=True))


def hardware_features(height=96, width=128) -> dict:
    """The dataset features lerobot-record derives for the hardware ur3e with one camera of that size."""

    robot = UR3e(
        UR3eConfig(
            host="192.0.2.1",
            cameras={"top": OpenCVCameraConfig(index_or_path=0, width=width, height=height, fps=20)},
        )
    )
    return {
        **hw_to_dataset_features(robot.action_features, "action"),
        **hw_to_dataset_features(robot.observation_features, "observation"),
    }


def episodes(root, repo_id):
    ds = LeRobotDataset(repo_id, root=root)
    frames = ds.hf_dataset.with_format("numpy")[:]
    return ds, [np.flatnonzero(frames["episode_index"] == e) for e in range(ds.meta.total_episodes)], frames


@pytest.mark.realtime  # the real-time twin records at 20 fps of wall time: beside other tests it drops frames
def test_lerobot_record_with_expert_teleop_on_the_twin(tmp_path):
    """Stock lerobot-record, headless, real-time twin: one expert demonstration per episode, each from a
    fresh scene, and the same dataset features as a hardware recording."""
    root = tmp_path / "demo"
    run_cli(
        "lerobot-record",
        "--robot.type=ur3e",
        "--robot.backend=sim",
        TWIN_CAMERA,
        "--teleop.type=ur3e_expert",
        "--dataset.repo_id=local/ur3e_demo",
        f"--dataset.root={root}",
        "--dataset.num_episodes=2",
        "--dataset.episode_time_s=7",
        "--dataset.reset_time_s=0.5",
        "--dataset.single_task=put the cube in the bowl",
        *RECORD_FLAGS,
    )
    ds, eps, frames = episodes(root, "local/ur3e_demo")
    assert ds.meta.robot_type == "ur3e" and len(eps) == 2
    for key, feature in hardware_features().items():
        assert ds.features[key]["shape"] == tuple(feature["shape"]) and ds.features[key].get(
            "names"
        ) == feature.get("names"), key
    for idx in eps:
        state, act = frames["observation.state"][idx], frames["action"][idx]
        assert len(idx) >= 100  # 7 s at 20 fps, minus what a busy machine drops
        np.testing.assert_allclose(state[0, :6], HOME_QPOS, atol=0.02)  # a new scene, the arm at home
        assert (
            act[:, 6].max() > 0.9 and state[:, 6].max() > 0.2
        )  # the expert closed the gripper on the object
        # The arm follows the commands: by the end it rests where it was last sent.
        np.testing.assert_allclose(state[-1, :6], act[-2, :6], atol=0.05)

    # Hardware-style labelling of the recording: two clicks per episode, color tracking, a labelled copy.
    env = PickPlaceEnv(observation_height=96, observation_width=128, segmentation=True)
    clicks, truth = {}, []
    for episode in range(2):  # the twin lays out scene k (seed k) for episode k
        truth.append(env.reset(seed=episode)[0]["segmentation"])
        clicks[str(episode)] = {"object": click_on(truth[-1], 1), "receptacle": click_on(truth[-1], 2)}
    env.close()
    (tmp_path / "clicks.json").write_text(json.dumps(clicks))
    run_cli(
        "condground",
        "prompts",
        "--dataset.repo_id=local/ur3e_demo",
        f"--dataset.root={root}",
        "--segmenter=color",
        f"--annotations={tmp_path / 'clicks.json'}",
        f"--output.root={tmp_path / 'labelled'}",
    )
    labelled, eps_l, frames_l = episodes(tmp_path / "labelled", "local/ur3e_demo")
    assert [len(i) for i in eps_l] == [len(i) for i in eps]
    for idx, seg in zip(eps_l, truth, strict=True):
        phase = frames_l[OBS_PHASE][idx].reshape(-1)
        assert phase[0] == 0 and phase[-1] == 1 and np.all(np.diff(phase) >= 0)  # acquire, then place
        first = decode_png(str(frames_l[OBS_SEGMENTATION][idx[0]]))
        # Against the twin's own labels. The object is ~15 px of an AV1-compressed frame, so its edge pixels
        # are lost (measured IoU 0.54-0.55); the bowl keeps 0.89.
        for label, least in ((1, 0.4), (2, 0.75)):
            iou = ((first == label) & (seg == label)).sum() / ((first == label) | (seg == label)).sum()
            assert iou > least, (label, iou)
        assert decode_png(str(frames_l[OBS_PROMPT_OBJECT][idx[0]])).shape == (64, 64, 3)

    # The other stock scripts drive the same robot: replay an episode, teleoperate with the expert.
    twin_flags = ["--robot.type=ur3e", "--robot.backend=sim", "--robot.sim.realtime=false", TWIN_CAMERA]
    run_cli(
        "lerobot-replay",
        *twin_flags,
        "--dataset.repo_id=local/ur3e_demo",
        f"--dataset.root={root}",
        "--dataset.episode=1",
        "--play_sounds=false",
    )
    proc = run_cli(
        "lerobot-teleoperate", *twin_flags, "--teleop.type=ur3e_expert", "--teleop_time_s=1", "--fps=20"
    )
    assert "Teleop loop time" in proc.stdout + proc.stderr


def test_expert_demonstrations_succeed_on_the_twin():
    robot, teleop = twin(condition="full_mixed"), UR3eExpert(UR3eExpertConfig())
    teleop.connect()
    with robot:
        for scene in range(2):
            if scene:
                robot.arm.reset_scene()
            for _ in range(300):
                robot.get_observation()
                robot.send_action(teleop.get_action())
                if teleop.expert.done:
                    break
            assert robot.arm.env.tracker.place, f"scene {scene}: the expert did not place the object"
    teleop.disconnect()


def test_lerobot_rollout_with_act_modified_checkpoint_on_the_twin(tmp_path):
    """Stock lerobot-rollout records policy episodes on the twin; the full variant gets its prompt crops
    from the robot's prompt cameras, and refuses to run without them."""
    ckpt = make_checkpoint(tmp_path / "ckpt", "full", 96, 128)
    common = [
        "lerobot-rollout",
        f"--policy.path={ckpt}",
        "--robot.type=ur3e",
        "--robot.backend=sim",
        "--robot.sim.realtime=false",
        TWIN_CAMERA,
        "--fps=20",
    ]
    root = tmp_path / "rollout"
    run_cli(
        *common,
        "--robot.prompts.segmenter=privileged",
        "--strategy.type=episodic",
        # Wall-clock seconds: beside a loaded suite 1.5 s held only the first frames, before any motion.
        "--dataset.episode_time_s=3",
        "--dataset.reset_time_s=0.2",
        "--dataset.repo_id=local/rollout_ur3e",
        f"--dataset.root={root}",
        "--dataset.single_task=put the cube in the bowl",
        "--dataset.num_episodes=2",
        "--dataset.push_to_hub=false",
        "--play_sounds=false",
    )
    ds, eps, frames = episodes(root, "local/rollout_ur3e")
    assert len(eps) == 2 and {
        "observation.images.prompt_object",
        "observation.images.prompt_receptacle",
    } <= set(ds.features)
    for idx in eps:
        np.testing.assert_allclose(frames["observation.state"][idx[0], :6], HOME_QPOS, atol=0.02)
    # The untrained policy's actions are its own (not the home pose), and the arm moved toward them.
    moved = np.abs(frames["observation.state"][:, :6] - HOME_QPOS).max()
    assert moved > 0.01, f"{len(frames['observation.state'])} frames, none away from home"

    proc = run_cli(
        *common, "--strategy.type=base", "--task=put the cube in the bowl", "--duration=1", check=False
    )
    assert (
        proc.returncode != 0
        and "needs ['observation.prompt.object', 'observation.prompt.receptacle']" in proc.stderr
    )


# ---------------------------------------------------------------------- safety
def test_bad_actions_are_refused_before_anything_is_sent():
    with twin() as robot:
        for bad, words in (
            ({**action(HOME_QPOS), "shoulder_pan.pos": float("nan")}, "7 finite numbers"),
            ({k: v for k, v in action(HOME_QPOS).items() if k != "gripper.pos"}, "missing ['gripper.pos']"),
            ({**action(HOME_QPOS), "elbow.vel": 0.0}, "unknown ['elbow.vel']"),
            ({**action(HOME_QPOS), "wrist_1.pos": "0.5"}, "got {'wrist_1.pos': 'str'}"),
            ({**action(HOME_QPOS), "wrist_1.pos": [0.5]}, "got {'wrist_1.pos': 'list'}"),
            ({**action(HOME_QPOS), "gripper.pos": np.zeros(1)}, "got {'gripper.pos': 'ndarray'}"),
            ({**action(HOME_QPOS), "gripper.pos": True}, "got {'gripper.pos': 'bool'}"),
        ):
            with pytest.raises(ValueError, match=words.replace("[", r"\[").replace("]", r"\]")):
                robot.send_action(bad)
        assert not robot.arm.loop.streaming and robot.arm.backend.servo_stops == 0


def test_joint_limits_step_and_workspace_are_clipped():
    with twin() as robot:
        q = HOME_QPOS.copy()
        sent = robot.send_action(action(q + [1.0, 0, -5.0, 0, 0, 0]))  # a jump and a joint past its limit
        assert sent["shoulder_pan.pos"] == pytest.approx(q[0] + 0.15)  # max_joint_step
        assert sent["elbow.pos"] == pytest.approx(q[2] - 0.15)
        # Drive the tool down through the table: every sent target keeps the tool in the box (z >= 5 mm).
        pos, rot = kinematics.forward(q)
        zs = []
        for _ in range(40):
            pos = pos + [0, 0, -0.02]
            target = kinematics.solve_ik(q, pos, rot)
            sent = robot.send_action(action(target))
            q = np.array([sent[k] for k in MOTOR_NAMES[:6]])
            zs.append(kinematics.forward(q)[0][2])
            robot.get_observation()
        assert min(zs) >= 0.005 - 1e-4 and min(zs) < 0.01  # it got down to the floor of the box, no further
        measured = robot.arm.state().q
        assert kinematics.forward(measured)[0][2] > 0.0


def test_stalled_command_stream_stops_the_arm_within_two_periods():
    robot = twin(realtime=True)
    with robot:
        arm = robot.arm
        q = HOME_QPOS.copy()
        for _ in range(8):  # a steady motion of the base joint at 1 rad/s, then silence
            q[0] += 0.05
            # Holding the lock keeps the physics thread still: the loop's clock at the command is exact, on a
            # loaded machine too (a wall-clock estimate is off by however long this thread was descheduled).
            with arm.lock:
                robot.send_action(action(q))
                sent_at = arm.env.data.time
                # On a loaded machine a sleep may outlast two periods: a stall the next command restarted.
                stalls_before = arm.state().stalls
            last = time.perf_counter()
            time.sleep(0.05)
        while arm.state().stalls == stalls_before:
            assert time.perf_counter() - last < 5.0, "the watchdog never stopped the stream"
            time.sleep(0.002)
        stopped = arm.state()
        # The simulation's own clock at the stop, not the state read afterwards: under load the physics thread
        # catches up in bursts and the first state the test sees may be a few ticks past the stop.
        assert 2 * 0.05 < arm.backend.stopped_at - sent_at <= 2 * 0.05 + 0.002 + 1e-9
        assert not stopped.streaming and arm.backend.servo_stops == stalls_before + 1
        time.sleep(0.5)
        assert np.abs(arm.state().qd).max() < 0.05  # standing still
        robot.send_action(action(q))  # the next command restarts the stream
        time.sleep(0.02)
        assert arm.state().streaming


def test_disconnect_stops_the_arm_on_an_exception():
    robot = twin(realtime=True)
    with pytest.raises(KeyboardInterrupt), robot:
        arm = robot.arm
        q = HOME_QPOS.copy()
        for _ in range(4):
            q[0] += 0.05
            robot.send_action(action(q))
            time.sleep(0.05)
        # On a loaded machine a sleep may outlast the watchdog's two periods and stop the stream early;
        # the last command restarts it, so the exception below always interrupts a streaming arm.
        robot.send_action(action(q))
        stops = arm.backend.servo_stops
        raise KeyboardInterrupt  # Ctrl-C in the middle of a motion
    assert not robot.is_connected and arm.backend.servo_stops == stops + 1 and not arm.loop.streaming
    assert ur3e_twin.TWINS == [] and arm.env is None


def test_missing_camera_is_one_clear_error_and_the_arm_is_released():
    robot = UR3e(
        UR3eConfig(
            backend="sim",
            cameras={"top": OpenCVCameraConfig(index_or_path="/dev/video97", width=128, height=96, fps=20)},
        )
    )
    with pytest.raises(ConnectionError, match="Camera 'top' \\(opencv\\) could not be opened"):
        robot.connect()
    assert not robot.is_connected and ur3e_twin.TWINS == []


@pytest.mark.parametrize(
    "kwargs, words",
    [
        ({"backend": "ros"}, "backend='ros'; allowed: rtde, sim"),
        ({"backend": "rtde"}, "host is required"),
        ({"backend": "sim", "gripper": "suction"}, "gripper='suction'"),
        ({"backend": "sim", "joint_offsets": [0.0] * 5}, "joint_offsets"),
        ({"backend": "sim", "max_joint_step": 2.0}, "max_joint_step=2.0"),
        (
            {"backend": "sim", "workspace_max": [0.5, float("nan"), 0.5]},
            "workspace_max=[0.5, nan, 0.5]: 3 finite",
        ),
        ({"backend": "sim", "stall_periods": float("inf")}, "stall_periods=inf; allowed: 1..50"),
        ({"backend": "sim", "stall_periods": float("nan")}, "stall_periods=nan; allowed: 1..50"),
        ({"host": "192.0.2.1", "prompts": {"segmenter": "privileged"}}, "needs backend=sim"),
    ],
)
def test_config_errors_name_the_bad_value(kwargs, words):
    if "prompts" in kwargs:
        kwargs["prompts"] = UR3ePromptsConfig(**kwargs["prompts"])
    with pytest.raises(ConfigError, match=words.replace("(", r"\(").replace("[", r"\[")):
        UR3eConfig(**kwargs)


KEYBOARD_SCRIPT = """
import time
import numpy as np
from lerobot_condground.robots import kinematics
from lerobot_condground.robots.config_ur3e import UR3eConfig, UR3eSimConfig
from lerobot_condground.robots.ur3e import UR3e
from lerobot_condground.teleoperators.config_ur3e_teleops import UR3eKeyboardConfig
from lerobot_condground.teleoperators.ur3e_teleops import UR3eKeyboard
robot = UR3e(UR3eConfig(backend="sim", sim=UR3eSimConfig(realtime=False)))
teleop = UR3eKeyboard(UR3eKeyboardConfig(step=0.01))
teleop.connect()
robot.connect()
start = kinematics.forward(robot.arm.state().q)[0]
print("ready", flush=True)
for _ in range(60):
    robot.get_observation()
    action = teleop.get_action()
    robot.send_action(action)
    time.sleep(0.02)
end = kinematics.forward(robot.arm.state().q)[0]
print("moved", *np.round(end - start, 4), "gripper", action["gripper.pos"], flush=True)
teleop.disconnect()
robot.disconnect()
"""


def test_keyboard_teleop_jogs_the_tool_with_ik():
    """Keys typed into the terminal (a pseudo-terminal here) move the tool in Cartesian steps."""

    master, slave = pty.openpty()
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.Popen(
        [sys.executable, "-c", KEYBOARD_SCRIPT],
        stdin=slave,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    os.close(slave)
    try:
        assert proc.stdout.readline().strip() == "ready"
        for key in "wwwiis ":  # +x three times, up twice, -x once, then the gripper
            os.write(master, key.encode())
            time.sleep(0.1)
        out, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
        os.close(master)
    moved = out.split()
    assert moved[0] == "moved", out + err[-2000:]
    dx, dy, dz, gripper = float(moved[1]), float(moved[2]), float(moved[3]), float(moved[5])
    assert dx == pytest.approx(0.02, abs=0.004) and abs(dy) < 0.004 and dz == pytest.approx(0.02, abs=0.004)
    assert gripper == 1.0


def test_live_prompt_cameras_track_the_clicked_entities():
    """--robot.prompts.segmenter=color: two clicks on the first frame give the prompt cameras, re-annotated
    at every recorded episode; they show what the twin's privileged crops show."""

    env = PickPlaceEnv(observation_height=96, observation_width=128, segmentation=True)
    obs, _ = env.reset(seed=0)  # the twin's first scene
    clicks = {"object": click_on(obs["segmentation"], 1), "receptacle": click_on(obs["segmentation"], 2)}
    env.close()
    robot = twin(prompts=UR3ePromptsConfig(segmenter="color", **clicks))
    assert robot.observation_features["prompt_object"] == (64, 64, 3)
    with robot:
        obs = robot.get_observation()
        truth = robot.arm.env._prompt_crops
        for key in ("prompt_object", "prompt_receptacle"):
            assert obs[key].shape == (64, 64, 3) and obs[key].dtype == np.uint8
            same = np.abs(obs[key].astype(int) - truth[key]).mean()
            other = np.abs(
                obs[key].astype(int)
                - truth["prompt_receptacle" if key == "prompt_object" else "prompt_object"]
            ).mean()
            assert same < other, (key, same, other)  # each crop shows its own entity
        robot.send_action(action(HOME_QPOS + [0.1, 0, 0, 0, 0, 0]))
        first = robot.get_observation()["prompt_object"]
        np.testing.assert_array_equal(first, obs["prompt_object"])  # fixed for the episode

    bad = twin(prompts=UR3ePromptsConfig(segmenter="color", object="500,20", receptacle=clicks["receptacle"]))
    with pytest.raises(ValueError, match="500"):
        bad.connect()
    assert not bad.is_connected and ur3e_twin.TWINS == []


def test_live_prompt_cameras_with_sam2_loaded_from_a_local_checkpoint(tmp_path):
    """The SAM 2 path of the prompt cameras, with a small random-weight model saved like a download: it
    loads the real way and yields the episode's two crops (what they show is meaningless)."""

    model = save_random_sam2(tmp_path / "sam2", size="small")
    robot = twin(
        prompts=UR3ePromptsConfig(
            segmenter="sam2", sam2_model_id=str(model), object="64,48", receptacle="20,30,50,60"
        )
    )
    with robot:
        first = robot.get_observation()
        robot.send_action(action(HOME_QPOS))
        again = robot.get_observation()
    for key in ("prompt_object", "prompt_receptacle"):
        assert first[key].shape == (64, 64, 3) and first[key].dtype == np.uint8
        np.testing.assert_array_equal(first[key], again[key])
