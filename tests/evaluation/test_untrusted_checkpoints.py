"""Checkpoints are untrusted input: loading one runs only installed code, and its identity covers every
file that decides behaviour."""

import hashlib
import json
import os
import shutil
import time
from pathlib import Path

import pytest

from helpers import run_cli
from lerobot_condground.core.configs import EvalEnvConfig, PolicyRefConfig
from lerobot_condground.diagnosis.attention import AttentionConfig, run_attention
from lerobot_condground.diagnosis.diagnose import DiagnoseConfig, run_diagnose
from lerobot_condground.diagnosis.probe import ProbeConfig, run_probe
from lerobot_condground.evaluation.checkpoints import checkpoint_hash, describe_checkpoint, load_policy
from lerobot_condground.evaluation.results import read_table
from lerobot_condground.evaluation.rollout import EnvSpec

PREPROCESSOR = "policy_preprocessor.json"


def with_step(src, dst, step: dict):
    """A copy of checkpoint src whose preprocessor runs `step` first."""
    shutil.copytree(src, dst)
    pipeline = json.loads((dst / PREPROCESSOR).read_text())
    pipeline["steps"].insert(0, step)
    (dst / PREPROCESSOR).write_text(json.dumps(pipeline))
    return dst


def test_a_checkpoint_naming_arbitrary_code_is_refused_before_anything_runs(tmp_path, act_checkpoint):
    marker = tmp_path / "pwned"
    evil = with_step(
        act_checkpoint,
        tmp_path / "evil",
        {"class": "subprocess.Popen", "config": {"args": ["touch", str(marker)]}},
    )
    proc = run_cli(
        "condground",
        "sweep",
        f"--policy.path={evil}",
        "--sweep.conditions=clean",
        "--eval.n_episodes=1",
        f"--output_dir={tmp_path / 'sweep'}",
        check=False,
    )
    assert proc.returncode == 2, proc.stderr[-3000:]
    # LeRobot's own plugin loader may print a line first; the error is one line, the last.
    assert (
        proc.stderr.strip()
        .splitlines()[-1]
        .startswith(
            f"condground sweep: Processor file {evil / PREPROCESSOR}, step 0 names class 'subprocess.Popen'"
        )
    )
    assert "--policy.trust_remote_code=true" in proc.stderr and "Traceback" not in proc.stderr
    assert not marker.exists() and not (tmp_path / "sweep").exists()

    # The same refusal for every command that loads a checkpoint, and for an unknown registry name.
    for run, config in (
        (run_probe, ProbeConfig),
        (run_diagnose, DiagnoseConfig),
        (run_attention, AttentionConfig),
    ):
        cfg = config(policy=PolicyRefConfig(path=str(evil)), output_dir=str(tmp_path / run.__name__))
        with pytest.raises(PermissionError, match="class 'subprocess.Popen'"):
            run(cfg)
    unknown = with_step(
        act_checkpoint, tmp_path / "unknown", {"registry_name": "steal_credentials", "config": {}}
    )
    with pytest.raises(PermissionError, match="registry name 'steal_credentials'"):
        describe_checkpoint(str(unknown))
    assert not marker.exists()

    # What the check prevents: opted in, LeRobot imports and calls the class (and rejects it, too late).
    loaded = describe_checkpoint(str(evil), trust_remote_code=True)
    spec = EnvSpec.for_checkpoint(EvalEnvConfig(task="PickPlaceFixedBin-v0"), loaded, "clean")
    with pytest.raises(
        ValueError, match=f"^{evil / PREPROCESSOR} does not build: .*must inherit from ProcessorStep"
    ):
        load_policy(str(evil), spec.lerobot_config(), trust_remote_code=True)
    deadline = time.time() + 30
    while not marker.exists() and time.time() < deadline:
        time.sleep(0.1)
    assert marker.exists()
    assert describe_checkpoint(str(act_checkpoint)).policy_type == "act"  # registered steps only: allowed


def test_the_checkpoint_hash_covers_processors_and_their_state(tmp_path, act_checkpoint):
    ckpt = tmp_path / "ckpt"
    shutil.copytree(act_checkpoint, ckpt)
    before = checkpoint_hash(str(ckpt))
    state_files = [
        step["state_file"]
        for step in json.loads((ckpt / PREPROCESSOR).read_text())["steps"]
        if "state_file" in step
    ]
    assert state_files, "the stock checkpoint's normalizer keeps its statistics in a state file"
    state = ckpt / state_files[0]
    data = bytearray(state.read_bytes())
    data[-1] ^= 1  # one bit of the normalization statistics
    state.write_bytes(bytes(data))
    assert checkpoint_hash(str(ckpt)) != before
    state.write_bytes(bytes(data[:-1]) + bytes([data[-1] ^ 1]))
    assert checkpoint_hash(str(ckpt)) == before
    pipeline = json.loads((ckpt / PREPROCESSOR).read_text())
    pipeline["steps"] = pipeline["steps"][::-1]
    (ckpt / PREPROCESSOR).write_text(json.dumps(pipeline))
    assert checkpoint_hash(str(ckpt)) != before


def test_a_damaged_checkpoint_file_is_named(tmp_path, act_checkpoint):
    for name in ("config.json", PREPROCESSOR, "train_config.json"):
        ckpt = tmp_path / name
        shutil.copytree(act_checkpoint, ckpt)
        text = (ckpt / name).read_text()
        (ckpt / name).write_text(text[: len(text) // 2])
        with pytest.raises(ValueError, match=f"{ckpt / name} is not valid JSON"):
            describe_checkpoint(str(ckpt))


def test_what_would_fail_inside_a_worker_fails_before_the_sweep_starts(tmp_path, act_checkpoint, capsys):
    from lerobot_condground.cli import main

    weights = tmp_path / "weights"
    shutil.copytree(act_checkpoint, weights)
    data = (weights / "model.safetensors").read_bytes()
    (weights / "model.safetensors").write_bytes(data[: len(data) - 1000])  # an interrupted copy
    unknown = tmp_path / "unknown"
    shutil.copytree(act_checkpoint, unknown)
    config = json.loads((unknown / "config.json").read_text())
    (unknown / "config.json").write_text(json.dumps({**config, "type": "act_plus_plus"}))
    retyped = tmp_path / "retyped"  # a type edited to another registered policy
    shutil.copytree(act_checkpoint, retyped)
    (retyped / "config.json").write_text(json.dumps({**config, "type": "diffusion"}))
    broken = with_step(
        act_checkpoint, tmp_path / "broken", {"registry_name": "normalizer_processor", "config": {}}
    )
    for ckpt, extra, fragment in (
        (retyped, [], f"Policy config {retyped / 'config.json'} names type 'diffusion', which has no field"),
        (retyped, [], "its fields are those of act"),
        (
            broken,
            ["--eval.n_episodes=1"],
            f"{broken / PREPROCESSOR} does not build: Failed to instantiate processor step 'normalizer_processor'",
        ),
        (weights, [], f"Weights file {weights / 'model.safetensors'} is damaged or incomplete"),
        (
            unknown,
            [],
            "names policy type 'act_plus_plus', which no installed package registers; known: act, ",
        ),
        (
            act_checkpoint,
            ["--eval.seed_offset=-1"],
            "--eval.seed_offset=-1 is not allowed; allowed: a seed from 0",
        ),
    ):
        out = tmp_path / f"sweep_{ckpt.name}"
        args = ["sweep", f"--policy.path={ckpt}", "--sweep.conditions=clean", f"--output_dir={out}", *extra]
        assert main(args) == 2
        assert fragment in capsys.readouterr().err.strip().splitlines()[-1]
        assert not out.exists()


def hub_snapshot(cache: Path, repo_id: str, files: Path, commit: str) -> Path:
    """`files` as huggingface_hub leaves a download of `commit`, now the repo's main: blobs by content, the
    snapshot's files linking to them."""
    repo = cache / f"models--{repo_id.replace('/', '--')}"
    snapshot = repo / "snapshots" / commit
    snapshot.mkdir(parents=True)
    for file in files.iterdir():
        blob = repo / "blobs" / hashlib.sha256(file.read_bytes()).hexdigest()
        blob.parent.mkdir(exist_ok=True)
        shutil.copyfile(file, blob)
        (snapshot / file.name).symlink_to(os.path.relpath(blob, snapshot))
    (repo / "refs").mkdir(exist_ok=True)
    (repo / "refs" / "main").write_text(commit)
    return snapshot


def test_a_hub_checkpoint_is_checked_and_loaded_from_one_snapshot(tmp_path, act_checkpoint, monkeypatch):
    import huggingface_hub.constants

    cache = tmp_path / "hub"
    monkeypatch.setenv("HF_HUB_CACHE", str(cache))
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(cache))
    repo_id = f"local/{tmp_path.name}"  # a snapshot is pinned once per process: a new id per test
    good = hub_snapshot(cache, repo_id, act_checkpoint, "a" * 40)
    sweep = [
        "condground", "sweep", f"--policy.path={repo_id}", "--sweep.conditions=clean", "--eval.n_episodes=1", "--eval.seeds=1",
        "--env.episode_length=5", "--workers=1", "--progress=false",
    ]  # fmt: skip
    # Offline from the cache, whose state files link out of the snapshot into the repo's blobs.
    run_cli(*sweep, f"--output_dir={tmp_path / 'sweep'}")
    rows = read_table(tmp_path / "sweep" / "results.parquet")
    assert set(rows.checkpoint) == {repo_id}
    assert set(rows.checkpoint_hash) == {checkpoint_hash(str(act_checkpoint))}

    described = describe_checkpoint(repo_id)
    assert described.read.folder == good
    assert (Path(described.local) / "config.json").read_bytes() == (good / "config.json").read_bytes()
    # The repo changes between the check and the load: this process loads what it checked.
    marker = tmp_path / "pwned"
    evil = with_step(
        act_checkpoint,
        tmp_path / "evil",
        {"class": "subprocess.Popen", "config": {"args": ["touch", str(marker)]}},
    )
    hub_snapshot(cache, repo_id, evil, "b" * 40)
    spec = EnvSpec.for_checkpoint(EvalEnvConfig(task="PickPlaceFixedBin-v0"), described, "clean")
    assert load_policy(repo_id, spec.lerobot_config()).hash == described.hash
    # A new process sees the new commit, and refuses it.
    refused = run_cli(*sweep, f"--output_dir={tmp_path / 'again'}", check=False)
    assert refused.returncode == 2 and "'subprocess.Popen'" in refused.stderr, refused.stderr[-2000:]
    time.sleep(0.5)
    assert not marker.exists()


READ_ONCE = """
import sys
from pathlib import Path

folder = Path(sys.argv[1]).resolve()
opened = []
sys.addaudithook(lambda event, args: event == "open" and isinstance(args[0], (str, Path))
                 and Path(args[0]).resolve().is_relative_to(folder) and opened.append(Path(args[0]).name))
from lerobot_condground.core.configs import EvalEnvConfig
from lerobot_condground.evaluation.checkpoints import describe_checkpoint, load_policy
from lerobot_condground.evaluation.rollout import EnvSpec

described = describe_checkpoint(str(folder))
spec = EnvSpec.for_checkpoint(EvalEnvConfig(task="PickPlaceFixedBin-v0"), described, "clean")
load_policy(described, spec.lerobot_config())
print(sorted(opened))
print(described.local)
"""


def test_a_checkpoint_is_read_once_and_its_private_copy_goes_with_the_process(tmp_path, act_checkpoint):
    """Describing and loading read each of the checkpoint's files once; LeRobot's loaders read the copy."""
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-c", READ_ONCE, str(act_checkpoint)], capture_output=True, text=True, check=True
    ).stdout.splitlines()
    opened = eval(out[-2])  # a list of file names, printed by the script above
    names = {p.name for p in act_checkpoint.iterdir() if p.is_file()}
    assert opened and set(opened) <= names
    assert len(opened) == len(set(opened)), opened
    assert not Path(out[-1]).exists()  # the private copy was removed when the process ended


def test_the_loader_loads_what_was_checked_when_the_folder_changes_after(tmp_path, act_checkpoint):
    import torch

    ckpt = tmp_path / "ckpt"
    shutil.copytree(act_checkpoint, ckpt)
    described = describe_checkpoint(str(ckpt))
    spec = EnvSpec.for_checkpoint(EvalEnvConfig(task="PickPlaceFixedBin-v0"), described, "clean")
    before = load_policy(described, spec.lerobot_config())
    marker = tmp_path / "pwned"
    with_step(
        act_checkpoint,
        tmp_path / "evil",
        {"class": "subprocess.Popen", "config": {"args": ["touch", str(marker)]}},
    )
    shutil.copy(
        tmp_path / "evil" / PREPROCESSOR, ckpt / PREPROCESSOR
    )  # a step that runs code, after the check
    (ckpt / "model.safetensors").write_bytes(b"\0" * 64)  # and other weights
    after = load_policy(described, spec.lerobot_config())
    assert after.hash == described.hash
    for (name, a), b in zip(before.policy.state_dict().items(), after.policy.state_dict().values()):
        assert torch.equal(a, b), name
    time.sleep(0.5)
    assert not marker.exists()
    with pytest.raises(ValueError, match="model.safetensors is damaged or incomplete"):
        describe_checkpoint(str(ckpt))  # read again, the changed folder is judged again
