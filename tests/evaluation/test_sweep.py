"""`condground sweep`: paired layouts, outcomes per episode, resuming after a kill, parallel and Ray
launchers giving the same rows, and one clear error per kind of bad input."""

import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pandas as pd
import pytest

from helpers import BIN, run_cli
from lerobot_condground.core.configs import EvalEnvConfig, PolicyRefConfig
from lerobot_condground.envs.assets import pool_assets
from lerobot_condground.evaluation.checkpoints import describe_checkpoint
from lerobot_condground.evaluation.results import (
    IDENTITY_COLUMNS,
    OUTCOME_COLUMNS,
    read_metadata,
    read_table,
    write_table,
)
from lerobot_condground.evaluation.rollout import EnvSpec
from lerobot_condground.evaluation.sweep import (
    MANIFEST,
    SweepConfig,
    SweepEvalConfig,
    SweepGridConfig,
    run_sweep,
)
from lerobot_condground.evaluation.units import PARTS

OUTCOMES = list(OUTCOME_COLUMNS)


def sweep_config(
    paths, out: Path, conditions="clean,full_mixed", seeds=1, episodes=2, batch=2, length=12, **kw
) -> SweepConfig:
    return SweepConfig(
        policy=PolicyRefConfig(paths=",".join(str(p) for p in paths)),
        env=EvalEnvConfig(task="PickPlaceRandomBin-v0", episode_length=length, **kw.pop("env", {})),
        sweep=SweepGridConfig(conditions=conditions),
        eval=SweepEvalConfig(seeds=seeds, n_episodes=episodes, batch_size=batch),
        output_dir=str(out),
        progress=False,
        **kw,
    )


def test_sweep_rows_are_paired_across_conditions_and_checkpoints(tmp_path, tiny_checkpoints):
    path = run_sweep(
        sweep_config(["expert", tiny_checkpoints[1]], tmp_path, seeds=2, episodes=2, length=160, workers=1)
    )
    rows = read_table(path)
    assert (
        len(rows) == 2 * 2 * 2 * 2
        and rows.duplicated(["checkpoint_hash", "condition", "eval_seed", "episode"]).sum() == 0
    )
    expert = rows[rows.policy_label == "expert"]
    assert expert.success.all() and (expert.stage == 3).all(), expert[["condition", "stage"]]
    assert (expert.grasped_first_match == "target").all() and (
        expert.target_location == "target_receptacle"
    ).all()
    ours = rows[rows.policy_label == "act_modified/full"]
    assert set(ours.training_seed) == {1} and ours.checkpoint_hash.nunique() == 1
    # The same (seed, episode) is the same layout everywhere: same seed and the same target receptacle pose.
    assert rows.groupby(["eval_seed", "episode"]).layout_seed.nunique().eq(1).all()
    assert rows.layout_seed.nunique() == 4
    assert rows.groupby("layout_seed")[["receptacle_x", "receptacle_y"]].nunique().eq(1).all().all()
    spec = json.loads(rows[rows.condition == "full_mixed"].condition_spec.iloc[0])
    assert spec == {f"{r}_{m}": 1 for r in ("object", "receptacle") for m in ("color", "shape", "neither")}
    meta = read_metadata(path)
    assert meta["kind"] == "sweep" and meta["grid"]["conditions"] == ["clean", "full_mixed"]
    assert [c["label"] for c in meta["checkpoints"]] == ["expert", "act_modified/full"] and "lerobot" in meta[
        "versions"
    ]


def test_killed_sweep_resumes_without_losing_or_repeating_episodes(tmp_path):
    out = tmp_path / "sweep"
    args = [
        str(BIN / "condground"),
        "sweep",
        "--policy.paths=expert",
        "--sweep.conditions=clean",
        "--eval.seeds=1",
        "--eval.n_episodes=6",
        "--eval.batch_size=1",
        "--env.episode_length=160",
        f"--output_dir={out}",
        "--workers=1",
        "--progress=false",
    ]
    env = {**os.environ, "MUJOCO_GL": "egl", "HF_HUB_OFFLINE": "1"}
    proc = subprocess.Popen(
        args, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True
    )
    deadline = time.time() + 120
    while (
        time.time() < deadline
        and len(list((out / PARTS).rglob("*.parquet")) if (out / PARTS).exists() else []) < 2
    ):
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    before = {p: p.stat().st_mtime_ns for p in (out / PARTS).rglob("*.parquet")}
    assert 2 <= len(before) < 6 and not (out / "results.parquet").exists()

    result = subprocess.run(args, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"{len(before)} already done" in result.stdout
    rows = read_table(out / "results.parquet")
    assert sorted(rows.episode) == list(range(6)) and (rows.stage == 3).all()
    assert all(p.stat().st_mtime_ns == t for p, t in before.items())  # finished units were not rerun


# Ray's start-up makes this the longest test (about 4 min quiet, 9 min beside trainings): `pytest -m slow`.
@pytest.mark.slow
def test_parallel_workers_and_ray_give_the_same_rows(tmp_path, tiny_checkpoints):
    runs = {}
    for name, kw in {
        "serial": {"workers": 1},
        "processes": {"workers": 2},
        "ray": {"workers": 2, "launcher": "ray"},
    }.items():
        path = run_sweep(
            sweep_config(
                [tiny_checkpoints[0]], tmp_path / name, conditions="full_mixed", episodes=4, batch=2, **kw
            )
        )
        runs[name] = read_table(path).sort_values(["eval_seed", "episode"], ignore_index=True)
    keys = list(IDENTITY_COLUMNS) + OUTCOMES
    for name in ("processes", "ray"):
        pd.testing.assert_frame_equal(runs[name][keys], runs["serial"][keys], check_dtype=False)
    assert (runs["serial"].steps == 12).all()


def test_a_sweep_among_augmentation_competitors_renders_them_and_pins_the_pool(tmp_path):
    """`--env.competitor_pool=augmentation` scores a policy among the copy-paste pool's rendered competitors
    (issue 55: novel assets against clutter); a sweep of the evaluation pool cannot resume it."""
    out = tmp_path / "aug"
    cfg = sweep_config(
        ["expert"], out, conditions="full_mixed", episodes=1, batch=1, length=3, workers=1,
        env={"competitor_pool": "augmentation"},
    )  # fmt: skip
    assert read_metadata(run_sweep(cfg))["grid"]["competitor_pool"] == "augmentation"
    env = EnvSpec.for_checkpoint(cfg.env, describe_checkpoint("expert"), "full_mixed").make()
    env.reset(seed=3)
    competitors = {e.asset for e in env.unwrapped.layout.entities[2:]}
    env.close()
    assert len(competitors) == 6 and not competitors & pool_assets("eval")
    with pytest.raises(
        ValueError, match=r"another grid; differences: competitor_pool: 'augmentation' -> None"
    ):
        run_sweep(sweep_config(["expert"], out, conditions="full_mixed", episodes=1, batch=1, length=3))
    with pytest.raises(
        ValueError, match="--env.competitor_pool='train' is not allowed; allowed: eval, augmentation"
    ):
        run_sweep(sweep_config(["expert"], tmp_path / "bad", env={"competitor_pool": "train"}))
    assert not (tmp_path / "bad").exists()


def test_bad_input_is_one_clear_error(tmp_path, tiny_checkpoints):
    ckpt = tiny_checkpoints[0]
    with pytest.raises(ValueError, match="Unknown condition 'object_colour_1'; allowed: clean"):
        run_sweep(sweep_config([ckpt], tmp_path / "a", conditions="clean,object_colour_1"))
    with pytest.raises(ValueError, match=r"does not fit .*camera 'top' at 96x128 \(env renders 64x96\)"):
        run_sweep(
            sweep_config([ckpt], tmp_path / "b", env={"observation_height": 64, "observation_width": 96})
        )
    other_robot = tmp_path / "other_robot"
    shutil.copytree(ckpt, other_robot)
    config = json.loads((other_robot / "config.json").read_text())
    config["output_features"]["action"]["shape"] = [14]
    (other_robot / "config.json").write_text(json.dumps(config))
    with pytest.raises(ValueError, match=r"expects action of shape \(14,\) \(env: \(7,\)\)"):
        run_sweep(sweep_config([other_robot], tmp_path / "b2"))
    with pytest.raises(FileNotFoundError, match="no/such/checkpoint"):
        run_sweep(sweep_config([tmp_path / "no/such/checkpoint"], tmp_path / "c"))

    # A checkpoint that fails only once a worker builds it: the run that finished no episode leaves nothing
    # (no manifest to pin its settings), and the corrected checkpoint runs in the same directory.
    broken = tmp_path / "broken"
    shutil.copytree(ckpt, broken)
    config = json.loads((broken / "config.json").read_text())
    (broken / "config.json").write_text(json.dumps({**config, "n_action_steps": config["chunk_size"] + 1}))
    with pytest.raises(Exception, match="Couldn't instantiate class ACTModifiedConfig"):
        run_sweep(sweep_config([broken], tmp_path / "c2", conditions="clean", length=3, workers=1))
    assert not (tmp_path / "c2").exists()
    (broken / "config.json").write_text(json.dumps(config))
    run_sweep(sweep_config([broken], tmp_path / "c2", conditions="clean", length=3, workers=1))
    assert len(read_table(tmp_path / "c2" / "results.parquet")) == 2

    out = tmp_path / "d"
    run_sweep(sweep_config([ckpt], out, conditions="clean", length=3, workers=1))
    with pytest.raises(ValueError, match="another grid; differences: n_episodes: 2 -> 4"):
        run_sweep(sweep_config([ckpt], out, conditions="clean", episodes=4, length=3, workers=1))
    relabelled = sweep_config([ckpt], out, conditions="clean", length=3, workers=1)
    relabelled.policy.label = "mine"  # rows under two labels would make the report refuse the directory
    with pytest.raises(ValueError, match=r"checkpoints \(path, hash, label\).*'mine'"):
        run_sweep(relabelled)
    manifest = (out / MANIFEST).read_text()
    (out / MANIFEST).write_text(manifest[: len(manifest) // 2])  # a hand edit gone wrong
    with pytest.raises(ValueError, match=f"Sweep manifest {out / MANIFEST} is not valid JSON"):
        run_sweep(sweep_config([ckpt], out, conditions="clean", length=3, workers=1))
    (out / MANIFEST).write_text(manifest)
    part = next((out / PARTS).rglob("*.parquet"))
    part.write_bytes(part.read_bytes()[:100])
    with pytest.raises(ValueError, match=f"Results file {part} is corrupted"):
        run_sweep(sweep_config([ckpt], out, conditions="clean", length=3, workers=1))
    # A part holding other episodes than its name says (e.g. copied from another sweep) is refused too.
    rows = read_table(out / "results.parquet")
    write_table(rows.assign(eval_seed=7), part)
    with pytest.raises(ValueError, match="does not match its unit .*eval_seed \\[7\\] instead of 0"):
        run_sweep(sweep_config([ckpt], out, conditions="clean", length=3, workers=1))

    proc = run_cli(
        "condground",
        "sweep",
        f"--policy.paths={ckpt}",
        "--sweep.conditions=full_mix",
        f"--output_dir={tmp_path / 'e'}",
        check=False,
    )
    assert proc.returncode == 2 and proc.stderr.strip().startswith(
        "condground sweep: Unknown condition 'full_mix'"
    )
    assert "Traceback" not in proc.stderr
