"""The trust gate judges what a checkpoint's processor steps would load, not only their names: one crafted
checkpoint per class of attack, refused by every command that loads a checkpoint, with a marker file that
would appear if anything ran."""

import importlib
import json
import pkgutil
import shutil

import pytest
from lerobot.processor.pipeline import ProcessorStepRegistry

from helpers import run_cli
from lerobot_condground.cli import main
from lerobot_condground.core.trust import DATA_STEPS, LOADING_STEPS, OPT_IN, REFUSED_STEPS, check_state_file
from lerobot_condground.evaluation.checkpoints import check_processor_steps, read_checkpoint, register_plugins

PREPROCESSOR = "policy_preprocessor.json"


def with_step(src, dst, step: dict, index: int = 0):
    """A copy of checkpoint src whose preprocessor has `step` at `index`."""
    shutil.copytree(src, dst)
    pipeline = json.loads((dst / PREPROCESSOR).read_text())
    pipeline["steps"].insert(index, step)
    (dst / PREPROCESSOR).write_text(json.dumps(pipeline))
    return dst


def shipped_code(folder, marker):
    """A processor folder whose auto_map points transformers at a module that leaves `marker` on import."""
    folder.mkdir(parents=True)
    (folder / "evil_processor.py").write_text(
        f"import pathlib\npathlib.Path({str(marker)!r}).touch()\n"
        "from transformers import ProcessorMixin\nclass Evil(ProcessorMixin):\n    attributes = []\n"
    )
    auto = {"auto_map": {"AutoProcessor": "evil_processor.Evil"}, "processor_class": "Evil"}
    for name in ("processor_config.json", "preprocessor_config.json"):
        (folder / name).write_text(json.dumps(auto))
    (folder / "config.json").write_text(json.dumps({**auto, "model_type": "evil"}))


def test_every_registered_step_was_reviewed():
    """A LeRobot upgrade or a new plugin step fails here until someone decides what a checkpoint may set."""
    import lerobot.policies

    register_plugins()
    for module in pkgutil.walk_packages(lerobot.policies.__path__, "lerobot.policies."):
        if module.name.rsplit(".", 1)[-1].startswith("processor_"):
            importlib.import_module(module.name)
    reviewed = DATA_STEPS | set(LOADING_STEPS) | set(REFUSED_STEPS)
    assert not DATA_STEPS & set(LOADING_STEPS) and not (DATA_STEPS | set(LOADING_STEPS)) & set(REFUSED_STEPS)
    assert set(ProcessorStepRegistry.list()) - reviewed == set()


@pytest.fixture
def marker(tmp_path):
    path = tmp_path / "pwned"
    yield path
    assert not path.exists(), "the checkpoint ran code"


def crafted(act_checkpoint, tmp_path, marker) -> dict:
    """name -> (checkpoint, what the one-line error must say)."""
    outside = tmp_path / "outside"
    shipped_code(outside, marker)
    cases = {
        # A LeRobot-registered step whose default (trust_remote_code=True) runs the folder's code.
        "shipped_code": (
            {"registry_name": "action_tokenizer_processor", "config": {"action_tokenizer_name": "fast"}},
            "step 0 (action_tokenizer_processor) sets trust_remote_code=True",
        ),
        "named_outside": (
            {"registry_name": "tokenizer_processor", "config": {"tokenizer_name": str(outside)}},
            f"step 0 (tokenizer_processor), field 'tokenizer_name', is '{outside}', a path outside",
        ),
        "dotdot_outside": (
            {"registry_name": "tokenizer_processor", "config": {"tokenizer_name": "../outside"}},
            "step 0 (tokenizer_processor), field 'tokenizer_name', is '../outside', a path outside",
        ),
        "refused_step": (
            {"registry_name": "groot_n1_7_vlm_encode_v1", "config": {"model_name": "fast"}},
            "step 0 (groot_n1_7_vlm_encode_v1) is refused: it loads its model_name's tokenizer",
        ),
        "state_outside": (
            {
                "registry_name": "normalizer_processor",
                "config": {},
                "state_file": str(outside / "x.safetensors"),
            },
            f"step 0: state_file '{outside / 'x.safetensors'}' is not a file inside the checkpoint's folder",
        ),
        "state_dotdot": (
            {"registry_name": "normalizer_processor", "config": {}, "state_file": "../x.safetensors"},
            "step 0: state_file '../x.safetensors' is not a file inside",
        ),
    }
    out = {}
    for name, (step, message) in cases.items():
        ckpt = with_step(act_checkpoint, tmp_path / name, step)
        shipped_code(ckpt / "fast", marker)
        out[name] = (ckpt, f"Processor file {ckpt / PREPROCESSOR}, {message}")
    return out


def commands(ckpt, out, dataset):
    """Every command that loads a checkpoint, with the least it needs to reach the checkpoint."""
    policy = f"--policy.path={ckpt}"
    data = [f"--dataset.repo_id=local/{dataset.name}", f"--dataset.root={dataset}"]
    return {
        "sweep": ["sweep", policy, "--sweep.conditions=clean", f"--output_dir={out}/sweep"],
        "probe": ["probe", policy, f"--output_dir={out}/probe"],
        "diagnose": ["diagnose", policy, f"--output_dir={out}/diagnose"],
        "attention": ["attention", policy, f"--output_dir={out}/attention"],
        "fit": ["fit", policy, *data, f"--output_dir={out}/fit"],
        "failures": ["failures", policy, f"--output_dir={out}/failures"],
        "subgoals": ["subgoals", policy, "--condition=cue", f"--output_dir={out}/subgoals"],
    }


def test_the_quickstart_checks_a_checkpoint_it_would_reuse_before_it_records(
    act_checkpoint, tmp_path, capsys
):
    marker = tmp_path / "pwned"
    evil = with_step(act_checkpoint, tmp_path / "evil", {"registry_name": "action_tokenizer_processor"})
    shipped_code(evil / "fast", marker)
    out = tmp_path / "quickstart"
    shutil.copytree(evil, out / "train" / "checkpoints" / "last" / "pretrained_model")
    assert main(["quickstart", f"--output_dir={out}", "--progress=false"]) == 2
    assert "sets trust_remote_code=True" in capsys.readouterr().err.strip().splitlines()[-1]
    assert sorted(p.name for p in out.iterdir()) == ["train"] and not marker.exists()


def test_each_class_is_refused_by_every_command_naming_the_file_step_and_field(
    act_checkpoint, plain_dataset, tmp_path, marker, capsys
):
    for name, (ckpt, message) in crafted(act_checkpoint, tmp_path, marker).items():
        for command, args in commands(ckpt, tmp_path / "runs" / name, plain_dataset).items():
            assert main(args) == 2, (name, command)
            last = capsys.readouterr().err.strip().splitlines()[-1]
            assert message in last, (name, command, last)
            # Opting in to code never lets a state file be read from outside the folder.
            assert ("state_file" in message) != (OPT_IN in last), (name, command, last)
        assert not (tmp_path / "runs" / name).exists(), name  # a refused run leaves nothing behind


def test_what_the_gate_lets_through(act_checkpoint, tmp_path):
    """A hub id, a tokenizer folder inside the checkpoint and remote code switched off pass; paths never do."""
    inside = with_step(
        act_checkpoint,
        tmp_path / "inside",
        {"registry_name": "tokenizer_processor", "config": {"tokenizer_name": "google/paligemma-3b-pt-224"}},
    )
    check_processor_steps(read_checkpoint(str(inside)), trust_remote_code=False)
    folder = with_step(
        act_checkpoint,
        tmp_path / "folder",
        {
            "registry_name": "action_tokenizer_processor",
            "config": {
                "action_tokenizer_name": str(tmp_path / "folder" / "fast"),
                "trust_remote_code": False,
            },
        },
    )
    check_processor_steps(read_checkpoint(str(folder)), trust_remote_code=False)
    state = with_step(
        act_checkpoint,
        tmp_path / "state",
        {"registry_name": "normalizer_processor", "config": {}, "state_file": "/etc/passwd"},
    )
    with pytest.raises(PermissionError, match="state_file '/etc/passwd'"):
        check_processor_steps(
            read_checkpoint(str(state)), trust_remote_code=True
        )  # opting in to code never moves a read out


def test_an_unreviewed_registered_step_is_refused(act_checkpoint, tmp_path):
    from dataclasses import dataclass

    from lerobot.processor import ObservationProcessorStep

    @ProcessorStepRegistry.register("test_unreviewed_step")
    @dataclass
    class Unreviewed(ObservationProcessorStep):
        def observation(self, observation):
            return observation

        def transform_features(self, features):
            return features

    try:
        ckpt = with_step(act_checkpoint, tmp_path / "ckpt", {"registry_name": "test_unreviewed_step"})
        with pytest.raises(PermissionError, match=r"step 0 \(test_unreviewed_step\) is not a step reviewed"):
            check_processor_steps(read_checkpoint(str(ckpt)), trust_remote_code=False)
        check_processor_steps(read_checkpoint(str(ckpt)), trust_remote_code=True)
    finally:
        ProcessorStepRegistry.unregister("test_unreviewed_step")


def test_what_the_gate_prevents_shipped_code_runs_once_trusted(act_checkpoint, tmp_path, monkeypatch):
    """Opted in, LeRobot's own tokenizer step runs the checkpoint's code: the refusal above is what stops it."""
    marker = tmp_path / "ran"
    ckpt = with_step(
        act_checkpoint,
        tmp_path / "ckpt",
        {"registry_name": "action_tokenizer_processor", "config": {"action_tokenizer_name": "PLACEHOLDER"}},
    )
    shipped_code(ckpt / "fast", marker)
    text = (ckpt / PREPROCESSOR).read_text().replace("PLACEHOLDER", str(ckpt / "fast"))
    (ckpt / PREPROCESSOR).write_text(text)
    monkeypatch.setenv("HF_MODULES_CACHE", str(tmp_path / "modules"))
    args = ["condground", "sweep", f"--policy.path={ckpt}", "--sweep.conditions=clean", "--eval.n_episodes=1"]
    refused = run_cli(*args, f"--output_dir={tmp_path / 'refused'}", check=False)
    assert refused.returncode == 2 and not marker.exists()
    trusted = run_cli(
        *args, "--policy.trust_remote_code=true", f"--output_dir={tmp_path / 'trusted'}", check=False
    )
    assert marker.exists(), trusted.stderr[-2000:]


def test_a_policy_type_that_loads_what_its_config_names_is_refused(act_checkpoint, tmp_path, capsys):
    """pi0_fast builds its action tokenizer with trust_remote_code=True from a name in config.json."""
    marker = tmp_path / "pwned"
    ckpt = tmp_path / "pi0_fast"
    shutil.copytree(act_checkpoint, ckpt)
    shipped_code(ckpt / "fast", marker)
    config = json.loads((ckpt / "config.json").read_text())
    (ckpt / "config.json").write_text(
        json.dumps({**config, "type": "pi0_fast", "action_tokenizer_name": str(ckpt / "fast")})
    )
    for command in ("sweep", "failures", "attention"):
        assert main([command, f"--policy.path={ckpt}", f"--output_dir={tmp_path / command}"]) == 2
        last = capsys.readouterr().err.strip().splitlines()[-1]
        assert (
            f"Policy config {ckpt / 'config.json'} names policy type 'pi0_fast', which is not reviewed"
            in last
        )
        assert OPT_IN in last and not (tmp_path / command).exists()
    assert not marker.exists()


def test_a_hub_snapshot_may_link_into_its_blobs_and_no_further(tmp_path, monkeypatch):
    repo = tmp_path / "models--someone--policy"
    snapshot = repo / "snapshots" / ("0" * 40)
    snapshot.mkdir(parents=True)
    (repo / "blobs").mkdir()
    (repo / "blobs" / "abc").write_bytes(b"state")
    (tmp_path / "secret").write_bytes(b"not the checkpoint's")
    (snapshot / "stats.safetensors").symlink_to("../../blobs/abc")  # as huggingface_hub leaves a download
    (snapshot / "leak.safetensors").symlink_to(tmp_path / "secret")
    processor = snapshot / "policy_preprocessor.json"
    check_state_file(processor, 0, {"state_file": "stats.safetensors"})
    for name in ("leak.safetensors", "../../blobs/abc"):
        with pytest.raises(PermissionError, match="is not a file inside the checkpoint's folder"):
            check_state_file(processor, 0, {"state_file": name})
    # A cache edited so that a snapshot file links elsewhere in the repo folder, or out of it, is refused whole.
    import huggingface_hub.constants

    from lerobot_condground.core.trust import pinned_folder

    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text("0" * 40)
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path))
    with pytest.raises(PermissionError, match="leak.safetensors .* links outside the repo's blobs"):
        pinned_folder("someone/policy")
    (snapshot / "leak.safetensors").unlink()
    (snapshot / "config.json").symlink_to("../../refs/main")
    with pytest.raises(PermissionError, match="config.json .* links outside the repo's blobs"):
        pinned_folder("someone/policy")
    (snapshot / "config.json").unlink()
    assert pinned_folder("someone/policy") == snapshot
    # The same links in a plain folder: its files must stay in it.
    plain = tmp_path / "plain"
    shutil.copytree(snapshot, plain, symlinks=True)
    with pytest.raises(PermissionError):
        check_state_file(plain / "policy_preprocessor.json", 0, {"state_file": "stats.safetensors"})
