"""InstrumentRouting-v0: the rule, the subgoal starts and checks, the expert as oracle, the labels, the
recording, and the stock lerobot-train / lerobot-eval on it."""

import dataclasses
import json

import numpy as np
import pytest

from helpers import read_json, run_cli
from lerobot_condground.core.routing import (
    DESTINATION,
    EPISODES,
    OTHER_CONTAINER,
    STATE_REGION,
    SUBGOALS,
    instruction,
)
from lerobot_condground.envs.expert import run_expert_episode
from lerobot_condground.envs.routing_env import InstrumentRoutingEnv
from lerobot_condground.envs.routing_expert import RoutingExpert


def _expert_results(episode: str, n: int, seed: int = 0) -> list[dict]:
    env = InstrumentRoutingEnv(subgoal=episode, obs_type="agent_pos")
    expert = RoutingExpert()
    results = [run_expert_episode(env, expert, seed + k, 300) for k in range(n)]
    env.close()
    return results


@pytest.mark.parametrize("episode", EPISODES)
def test_the_expert_reaches_each_subgoal_from_its_own_start(episode):
    results = _expert_results(episode, 12, seed=500)
    assert all(r["is_success"] for r in results), [r["reached"] for r in results]
    if episode == "procedure":
        assert {r["reached"] for r in results} == {",".join(SUBGOALS)}
        assert all(r["placed_in"] == r["destination"] == r["route_choice"] for r in results)
    else:
        assert {r["reached"] for r in results} == {episode}
    # Both states occur, and the rule decides the side.
    if episode in ("route", "place"):
        assert {r["contaminated"] for r in results} == {True, False}
        assert all(r["destination"] == ("left" if r["contaminated"] else "right") for r in results)


@pytest.mark.slow
@pytest.mark.parametrize("episode", EPISODES)
def test_the_expert_succeeds_in_99_percent_over_200_episodes(episode):
    results = _expert_results(episode, 200)
    assert sum(r["is_success"] for r in results) >= 198, [
        r["reached"] for r in results if not r["is_success"]
    ]


class _WrongWay(RoutingExpert):
    """Routes to the other container: a policy that ignored the mark."""

    def _start(self, phase):
        layout = self.env.layout
        if phase == "route":
            self.env.layout = dataclasses.replace(layout, contaminated=not layout.contaminated)
        try:
            super()._start(phase)
        finally:
            self.env.layout = layout


def test_an_instrument_let_go_in_the_other_container_ends_the_episode_as_a_failure():
    env = InstrumentRoutingEnv(subgoal="place", obs_type="agent_pos")
    expert = _WrongWay()
    info = run_expert_episode(env, expert, 3, 300)
    assert not info["is_success"] and info["stage"] == 0
    assert info["placed_in"] == info["route_choice"] != info["destination"]
    env.close()


def test_labels_follow_the_state_and_the_instructions_have_two_forms():
    env = InstrumentRoutingEnv(
        subgoal="route", segmentation=True, observation_height=96, observation_width=128
    )
    sides_seen = set()
    for seed in range(6):
        obs, info = env.reset(seed=seed)
        sides_seen.add(info["destination"])
        top = obs["segmentation"]
        assert {DESTINATION, OTHER_CONTAINER, STATE_REGION} <= set(np.unique(top).tolist())
        # The destination's pixels lie on its side of the image: the scene camera faces the robot, so the
        # robot's left (+y) is the image's right.
        cols = np.nonzero(top == DESTINATION)[1].mean()
        assert (cols > top.shape[1] / 2) == (info["destination"] == "left")
        assert obs["segmentation_wrist"].shape == (96, 128)
        assert obs["pixels"]["wrist"].shape == (96, 128, 3)
        assert env.task_description == "move the instrument over the highlighted container"
        assert env.explicit_instruction() == f"move the instrument over the {info['destination']} container"
    assert sides_seen == {"left", "right"}
    # The mark is what differs: same seed, state flipped by hand, the state region changes colour.
    obs, _ = env.reset(seed=1)
    region = obs["segmentation"] == STATE_REGION
    before = obs["pixels"]["top"][region].mean(0)
    import mujoco

    from lerobot_condground.envs.routing_scene import MARK, STEEL

    gid = env.model.geom("mark").id
    env.model.geom_rgba[gid] = STEEL if np.allclose(env.model.geom_rgba[gid], MARK) else MARK
    mujoco.mj_forward(env.model, env.data)
    after = env._render_rgb("top")[region].mean(0)
    assert np.abs(before - after).max() > 40
    env.close()


@pytest.mark.parametrize(
    "call, message",
    [
        (
            lambda: InstrumentRoutingEnv(subgoal="grasp"),
            "subgoal='grasp' is not allowed; allowed: procedure, pick",
        ),
        (lambda: InstrumentRoutingEnv(subgoal="pick,pick"), "each once"),
        (lambda: instruction("route", "explicit"), "needs the destination"),
        (lambda: instruction("route", "polite"), "Unknown instruction form 'polite'"),
    ],
)
def test_bad_subgoals_and_forms_are_refused(call, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        call()


def test_env_config_flags_that_do_not_apply_are_refused():
    from lerobot_condground.core.configs import ConfigError
    from lerobot_condground.envs.configs import CondGroundEnvConfig

    with pytest.raises(
        ConfigError, match="--env.condition='full_mixed' does not apply to InstrumentRouting-v0"
    ):
        CondGroundEnvConfig(task="InstrumentRouting-v0", condition="full_mixed")
    with pytest.raises(
        ConfigError, match="--env.competitor_pool='augmentation' does not apply to InstrumentRouting-v0"
    ):
        CondGroundEnvConfig(task="InstrumentRouting-v0", competitor_pool="augmentation")
    with pytest.raises(
        ConfigError, match="--env.competitor_pool='train' is not allowed; allowed: eval, augmentation"
    ):
        CondGroundEnvConfig(task="PickPlaceFixedBin-v0", competitor_pool="train")
    with pytest.raises(ConfigError, match="--env.subgoal='route' applies to InstrumentRouting-v0 only"):
        CondGroundEnvConfig(task="PickPlaceRandomBin-v0", subgoal="route")
    cfg = CondGroundEnvConfig(task="InstrumentRouting-v0")
    assert cfg.wrist_camera and not cfg.prompts and "pixels/wrist" in cfg.features
    assert not CondGroundEnvConfig(task="PickPlaceRandomBin-v0").wrist_camera


def test_a_recording_holds_both_cameras_the_instructions_and_the_masks(routing_dataset):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_condground.core.labels import decode_png

    ds = LeRobotDataset("local/routing", root=routing_dataset)
    assert {"observation.images.top", "observation.images.wrist", "observation.segmentation",
            "observation.segmentation_wrist", "observation.destination", "observation.phase"} <= set(ds.meta.features)  # fmt: skip
    provenance = read_json(routing_dataset / "meta" / "condground_record.json")
    assert provenance["env"]["subgoal"] == "procedure,place"
    episodes = provenance["episodes"]
    assert {e["subgoal"] for e in episodes} <= {"procedure", "place"}
    for index, episode in enumerate(episodes):
        frames = [ds[i] for i in range(len(ds)) if int(ds[i]["episode_index"]) == index]
        destination = next(e["side"] for e in episode["entities"] if e["role"] == "destination")
        assert {int(f["observation.destination"]) for f in frames} == {["left", "right"].index(destination)}
        tasks = [f["task"] for f in frames]
        phases = [int(f["observation.phase"]) for f in frames]
        assert phases == sorted(phases)  # the procedure's steps, in order
        if episode["subgoal"] == "procedure":
            assert set(phases) == set(range(7))
            assert list(dict.fromkeys(tasks)) == [instruction(s) for s in SUBGOALS]
        else:
            assert set(tasks) == {instruction("place")}
        seg = decode_png(frames[0]["observation.segmentation"])
        assert seg.shape == (96, 128) and DESTINATION in seg and STATE_REGION in seg


def test_stock_lerobot_train_and_eval_run_the_routing_task(tmp_path):
    from test_lerobot_scripts import TINY_ACT

    root = tmp_path / "plain"
    run_cli(
        "condground", "record", "--env.task=InstrumentRouting-v0", "--env.subgoal=route",
        "--env.observation_height=96", "--env.observation_width=128", "--dataset.repo_id=local/routing_plain",
        f"--dataset.root={root}", "--dataset.num_episodes=1", "--dataset.labels=false", "--progress=false",
    )  # fmt: skip
    out = tmp_path / "train"
    run_cli(
        "lerobot-train", *TINY_ACT, "--dataset.repo_id=local/routing_plain", f"--dataset.root={root}",
        "--batch_size=2", "--steps=2", "--save_freq=2", "--num_workers=0", f"--output_dir={out}",
        "--wandb.enable=false",
    )  # fmt: skip
    checkpoint = out / "checkpoints" / "last" / "pretrained_model"
    features = read_json(checkpoint / "config.json")["input_features"]
    assert set(features) == {"observation.images.top", "observation.images.wrist", "observation.state"}
    run_cli(
        "lerobot-eval", f"--policy.path={checkpoint}", "--env.type=condground", "--env.task=InstrumentRouting-v0",
        "--env.subgoal=route,place", "--env.cue=true", "--env.observation_height=96", "--env.observation_width=128",
        "--env.episode_length=10", "--eval.n_episodes=2", "--eval.batch_size=2", f"--output_dir={tmp_path / 'eval'}",
    )  # fmt: skip
    info = json.loads((tmp_path / "eval" / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 2
    assert all(r in (0.0, 1.0) for r in info["per_task"][0]["metrics"]["max_rewards"])


def test_commands_of_the_condition_grid_point_the_routing_task_to_its_evaluation(tmp_path, capsys):
    from lerobot_condground.cli import main

    code = main(
        ["sweep", "--policy.paths=expert", "--env.task=InstrumentRouting-v0", f"--output_dir={tmp_path}"]
    )
    err = capsys.readouterr().err
    assert code == 2 and "InstrumentRouting-v0 has no competitor conditions" in err and "--env.subgoal" in err
