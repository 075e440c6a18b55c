"""`condground failures`: the tracer's events on real rollouts, and the cause each outcome gets."""

import numpy as np
import pandas as pd
import pytest

from helpers import garbage_checkpoints, read_json, run_cli
from lerobot_condground.diagnosis.failures import CAUSES, Tracer, cause, summarize
from lerobot_condground.evaluation.checkpoints import describe_checkpoint
from lerobot_condground.evaluation.rollout import EnvSpec, run_episodes


def test_the_expert_closes_once_on_the_cube_without_pushing_it():
    spec = EnvSpec(
        task="PickPlaceFixedBin-v0", condition="clean", observation_height=96, observation_width=128
    )
    envs = [spec.make() for _ in range(2)]
    tracer = Tracer(envs, spec.fps)
    outcomes = run_episodes(describe_checkpoint("expert"), envs, [3, 4], spec.episode_length, on_step=tracer)
    for i, outcome in enumerate(outcomes):
        measured = tracer.measurements(i, outcome["truncated"])
        assert outcome["success"] and measured["closings"] == 1, measured
        assert measured["first_close_offset_cm"] < 1.0 and measured["pushed_cm"] < 0.5, measured
        assert 0 < measured["first_close_step"] < outcome["steps"], measured
        # It lets go once, over the bowl's centre, after it closed.
        assert measured["first_close_step"] < measured["release_step"] < outcome["steps"], measured
        assert measured["release_offset_cm"] < 2.0 and not measured["held_at_end"], measured
        assert cause({**outcome, **measured}) == "success"


OUTCOME = dict(
    success=False, physics_unstable=False, target_x=0.4, target_y=0.0, target_z=0.02, pick=False, lift=False,
    selected_competitor_object=False, placed_in_competitor_receptacle=False, pushed_cm=0.0, closings=0,
)  # fmt: skip


@pytest.mark.parametrize(
    "changes, expected",
    [
        (dict(success=True, pick=True, lift=True), "success"),
        (dict(physics_unstable=True, target_z=-1.0), "unstable"),
        (dict(target_z=-0.3, pick=True), "cube_off_table"),
        (dict(selected_competitor_object=True, pick=True), "wrong_object"),
        (dict(placed_in_competitor_receptacle=True, pick=True, lift=True), "wrong_receptacle"),
        (dict(pick=True, lift=True, closings=2), "lifted_not_placed"),
        (dict(pick=True, closings=1), "picked_not_lifted"),
        (dict(pushed_cm=5.0, closings=1), "pushed_away"),
        (dict(pushed_cm=1.0, closings=3), "closed_off_target"),
        ({}, "never_closed"),
    ],
)
def test_each_failure_gets_the_first_cause_that_applies(changes, expected):
    assert cause({**OUTCOME, **changes}) == expected


def test_failures_command_on_a_checkpoint(tiny_checkpoints, tmp_path):
    out = tmp_path / "failures"
    run_cli(
        "condground", "failures", f"--policy.path={tiny_checkpoints[0]}", "--env.task=PickPlaceRandomBin-v0",
        "--env.episode_length=30", "--failures.episodes=3", "--failures.batch_size=2", f"--output_dir={out}",
        "--progress=false",
    )  # fmt: skip
    rows = pd.read_parquet(out / "episodes.parquet")
    assert list(rows["episode"]) == [0, 1, 2] and list(rows["layout_seed"]) == [
        1_000_000,
        1_000_001,
        1_000_002,
    ]
    assert set(rows["cause"]) <= set(CAUSES) and not rows["success"].any()
    result = read_json(out / "failures.json")
    assert sum(result["causes"].values()) == 3 and result["servo"] == "interpolated"
    assert np.isfinite(rows["pushed_cm"]).all()
    # The phase head ran once per 10-step chunk of each 30-step rollout; a random policy never holds the
    # cube, so each place prediction is one made without it.
    for _, row in rows.iterrows():
        assert len(row["phase_predicted"]) == len(row["phase_world"]) == -(-row["steps"] // 10) == 3
        assert list(row["phase_steps"]) == [0, 10, 20]
        assert not row["phase_world"].any()
        assert row["place_phase_unheld"] == row["phase_predicted"].sum()
        assert row["phase_agreement"] == pytest.approx(1 - row["phase_predicted"].mean())
    assert result["phase"]["failures_with_place_phase_unheld"] == (rows["place_phase_unheld"] > 0).sum()


def test_bad_input_is_one_line(tiny_checkpoints, tmp_path, capsys):
    from lerobot_condground.cli import main

    for flag, message in (
        ("--failures.episodes=0", "--failures.episodes=0"),
        ("--env.task=InstrumentRouting-v0", "use `condground subgoals`"),
        ("--env.condition=object_color_9", "object_color_9"),
    ):
        code = main(
            ["failures", f"--policy.path={tiny_checkpoints[0]}", flag, f"--output_dir={tmp_path / 'out'}"]
        )
        err = capsys.readouterr().err
        assert code == 2 and message in err.strip().splitlines()[-1], err
        assert not (tmp_path / "out").exists()
    for checkpoint, message in garbage_checkpoints(tiny_checkpoints[0], tmp_path).items():
        code = main(["failures", f"--policy.path={checkpoint}", f"--output_dir={tmp_path / 'out'}"])
        err = capsys.readouterr().err
        assert code == 2 and message in err.strip().splitlines()[-1], err
        assert not (tmp_path / "out").exists()


def test_the_carry_splits_lifted_not_placed_into_released_slipped_and_held():
    nan = float("nan")
    rows = pd.DataFrame(
        {
            "success": [True, False, False, False, False],
            "cause": [
                "success",
                "lifted_not_placed",
                "lifted_not_placed",
                "lifted_not_placed",
                "never_closed",
            ],
            "closings": [1, 1, 2, 1, 0],
            "stalled": [False] * 5,
            "first_close_offset_cm": [0.5, 1.0, 2.0, 1.5, nan],
            "release_step": [120, 150, -1, -1, -1],
            "release_offset_cm": [0.8, 9.0, nan, nan, nan],
            "held_at_end": [False, False, False, True, False],
        }
    )
    carry = summarize(rows)["carry"]
    assert (carry["released"], carry["slipped"], carry["held_to_end"]) == (1, 1, 1)
    assert carry["release_offset_cm"] == {"success_median": 0.8, "failure_median": 9.0}
