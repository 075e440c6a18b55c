"""`condground probe`: the swapped prompt really shows the competitor, and the probe pairs its runs."""

import json

import numpy as np
import pytest

from helpers import make_checkpoint
from lerobot_condground.core.configs import EvalEnvConfig, PolicyRefConfig
from lerobot_condground.diagnosis.probe import ProbeConfig, ProbeSettings, run_probe
from lerobot_condground.envs.pickplace_env import PickPlaceEnv
from lerobot_condground.evaluation.results import read_table


def test_swap_prompt_shows_the_competitor():
    env = PickPlaceEnv(
        task="PickPlaceRandomBin-v0",
        condition="receptacle_color_1",
        prompts=True,
        observation_height=96,
        observation_width=128,
    )
    obs, _ = env.reset(seed=3)
    target = obs["prompt_receptacle"]
    competitor = next(e for e in env.layout.entities if e.asset.role == "receptacle" and not e.is_target)
    swapped = env.swap_prompt("receptacle", competitor.label)
    assert swapped.shape == target.shape and swapped.any()
    assert np.abs(swapped.astype(int) - target.astype(int)).mean() > 5  # another shape of the same color
    obs, *_ = env.step(np.concatenate([env.joint_positions(), [0.0]]))
    assert np.array_equal(obs["prompt_receptacle"], swapped) and np.array_equal(
        obs["prompt_object"], env.reset(seed=3)[0]["prompt_object"]
    )
    assert np.array_equal(
        env.reset(seed=3)[0]["prompt_receptacle"], target
    )  # a reset restores the target's crop
    with pytest.raises(
        ValueError, match="Entity 1 is not a receptacle of this scene; receptacle labels here: \\[2, 3\\]"
    ):
        env.swap_prompt("receptacle", 1)
    env.close()


def test_probe_runs_each_layout_with_both_prompts(tmp_path, tiny_checkpoints):
    cfg = ProbeConfig(
        policy=PolicyRefConfig(path=str(tiny_checkpoints[0])),
        env=EvalEnvConfig(task="PickPlaceRandomBin-v0", episode_length=8),
        probe=ProbeSettings(role="receptacle", match="shape", episodes=3, batch_size=3),
        output_dir=str(tmp_path / "probe"),
        workers=1,
        progress=False,
    )
    summary = json.loads(run_probe(cfg).read_text())
    assert summary["kind"] == "probe" and summary["condition"] == "receptacle_shape_1"
    assert summary["target"]["n"] == summary["swapped"]["n"] == 3 and summary["difference"]["n"] == 3
    assert 0 <= summary["target"]["low"] <= summary["target"]["high"] <= 1
    rows = read_table(tmp_path / "probe" / "results.parquet")
    assert sorted(rows.prompt) == ["swapped"] * 3 + ["target"] * 3
    # Both prompts ran the same layouts.
    assert rows.groupby("episode").layout_seed.nunique().eq(1).all() and rows.layout_seed.nunique() == 3


def test_probe_refuses_a_policy_without_prompts(tmp_path):
    ckpt = make_checkpoint(tmp_path / "standard", variant="standard")
    cfg = ProbeConfig(policy=PolicyRefConfig(path=str(ckpt)), output_dir=str(tmp_path / "out"))
    with pytest.raises(
        ValueError, match="needs a checkpoint that reads visual prompts.*'act_modified/standard'"
    ):
        run_probe(cfg)
    with pytest.raises(ValueError, match="Unknown --probe.role='cup'; allowed: object, receptacle"):
        run_probe(ProbeConfig(policy=PolicyRefConfig(path=str(ckpt)), probe=ProbeSettings(role="cup")))
    # Another command's folder (a subgoals run's operator-scored trials) is never overwritten.
    (tmp_path / "subgoals").mkdir()
    (tmp_path / "subgoals" / "subgoals.json").write_text("{}")
    with pytest.raises(FileExistsError, match="holds subgoals.json, another command's results"):
        run_probe(ProbeConfig(policy=PolicyRefConfig(path=str(ckpt)), output_dir=str(tmp_path / "subgoals")))
    assert sorted(p.name for p in (tmp_path / "subgoals").iterdir()) == ["subgoals.json"]
