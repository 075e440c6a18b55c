"""`pi05_grounded` on LeRobot's real pi05 code at a reduced size (`pi05_tiny`), with a local tokenizer and
HF_HUB_OFFLINE=1: flags, processors saved and reloaded, the attention capture, eq. (1) and its gradients
with and without gradient checkpointing, strict weight loading, the full size on the meta device, and
`condground pi05-start` followed by the stock `lerobot-train --policy.path`."""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import draccus
import pandas as pd
import pytest
import torch
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.factory import make_pre_post_processors
from lerobot.policies.pi05.configuration_pi05 import PI05Config
from lerobot.policies.pi05.modeling_pi05 import PI05Policy

from helpers import read_json, run_cli
from lerobot_condground.core.grounding import pooled_mask
from lerobot_condground.core.routing import DESTINATION, OTHER_CONTAINER, STATE_REGION, STEPS, instruction
from lerobot_condground.policies.pi05_grounded.configuration_pi05_grounded import PI05GroundedConfig
from lerobot_condground.policies.pi05_grounded.modeling_pi05_grounded import (
    ExpertAttention,
    PI05GroundedPolicy,
)
from lerobot_condground.policies.pi05_grounded.processor_pi05_grounded import (
    make_pi05_grounded_pre_post_processors,
)
from pi05_tiny import PATCH, save_tokenizer, tiny_pi05

H, W, RES, CHUNK, B = 48, 64, 32, 4, 2
GRID = RES // PATCH
CAMERAS = ("observation.images.top", "observation.images.wrist")
LABELS = (
    "observation.segmentation",
    "observation.segmentation_wrist",
    "observation.phase",
    "observation.destination",
)


@pytest.fixture(scope="module")
def tokenizer(tmp_path_factory):
    return save_tokenizer(tmp_path_factory.mktemp("tokenizer"))


def make_config(tokenizer, cls=PI05GroundedConfig, labels=LABELS, **kw) -> PI05Config:
    if cls is PI05GroundedConfig:
        kw.setdefault("tokenizer_name", str(tokenizer))
    cfg = cls(
        device="cpu", dtype="float32", chunk_size=CHUNK, n_action_steps=CHUNK, max_state_dim=8, max_action_dim=8,
        image_resolution=(RES, RES), tokenizer_max_length=128, num_inference_steps=2, **kw,
    )  # fmt: skip
    cfg.input_features = {c: PolicyFeature(FeatureType.VISUAL, (3, H, W)) for c in CAMERAS}
    cfg.input_features["observation.state"] = PolicyFeature(FeatureType.STATE, (7,))
    cfg.input_features |= {key: PolicyFeature(FeatureType.STATE, (1,)) for key in labels}
    cfg.output_features = {"action": PolicyFeature(FeatureType.ACTION, (7,))}
    return cfg


def cache_repo(cache: Path, repo_id: str, files: Path) -> Path:
    """`files` as the snapshot of hub repo `repo_id` in hub cache `cache`; returns the snapshot folder."""
    repo = cache / f"models--{repo_id.replace('/', '--')}"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text("0" * 40)
    snapshot = repo / "snapshots" / ("0" * 40)
    shutil.copytree(files, snapshot)
    return snapshot


def make_policy(cfg, cls=PI05GroundedPolicy, seed=0):
    torch.manual_seed(seed)
    with tiny_pi05():
        policy = cls(cfg)
    with torch.no_grad():  # pi05's adaRMS projections start at zero; give every path a gradient
        for name, p in policy.named_parameters():
            if ".dense." in name:
                p.normal_(0, 0.02)
    return policy


def stats():
    one = {"mean": torch.zeros(7), "std": torch.ones(7), "q01": -torch.ones(7), "q99": torch.ones(7)}
    return {"observation.state": one, "action": dict(one)}


def raw_batch(seed=0):
    """Steps route and inspect; the destination (label 2) in the top-left, the other container (3) at the
    bottom right, the state region (4) in the middle."""
    g = torch.Generator().manual_seed(seed)
    seg = torch.zeros(B, H, W, dtype=torch.uint8)
    seg[:, 0:12, 0:16] = DESTINATION
    seg[:, 36:48, 48:64] = OTHER_CONTAINER
    seg[:, 20:28, 28:36] = STATE_REGION
    return {
        **{c: torch.rand(B, 3, H, W, generator=g) for c in CAMERAS},
        "observation.state": torch.rand(B, 7, generator=g),
        "action": torch.rand(B, CHUNK, 7, generator=g),
        "action_is_pad": torch.zeros(B, CHUNK, dtype=torch.bool),
        "observation.segmentation": seg,
        "observation.segmentation_wrist": seg.clone(),
        "observation.phase": torch.tensor([[STEPS.index("route")], [STEPS.index("inspect")]]),
        "observation.destination": torch.tensor([[0], [1]]),
        "task": [instruction("route"), instruction("inspect")],
    }


def test_registered_presets_and_flags():
    @dataclass
    class Args:
        policy: PreTrainedConfig

    cfg = draccus.parse(Args, args=["--policy.type=pi05_grounded", "--policy.variant=cue", "--policy.grounding_heads=[0,3]", "--policy.tokenizer_name=/tok"]).policy  # fmt: skip
    assert type(cfg) is PI05GroundedConfig and isinstance(cfg, PI05Config)
    assert (cfg.cue, cfg.use_grounding_loss, cfg.instruction) == (True, False, "generic")
    assert cfg.grounding_heads == [0, 3] and cfg.tokenizer_name == "/tok"
    regularized = PI05GroundedConfig(instruction="generic")
    assert (regularized.use_grounding_loss, regularized.cue, regularized.instruction) == (
        True,
        False,
        "generic",
    )


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (
            {"variant": "prompted"},
            "Unknown pi05_grounded variant 'prompted'; allowed: plain, cue, regularized",
        ),
        ({"instruction": "vague"}, "instruction='vague' is not allowed; allowed: generic, explicit"),
        ({"grounding_neg_weight": -1.0}, "grounding_neg_weight=-1.0 is not allowed"),
        ({"grounding_heads": [8]}, "grounding_heads=[8] are not allowed; allowed: 0..7"),
        ({"grounding_layers": []}, "grounding_layers=[] is not allowed"),
    ],
)
def test_bad_settings_are_one_clear_error(kwargs, message):
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]").replace("(", r"\(")):
        PI05GroundedConfig(**kwargs)


def test_bad_layers_missing_labels_and_unreachable_tokenizer(tokenizer, tmp_path):
    with pytest.raises(
        ValueError, match=r"grounding_layers=\[2\] are not layers of the action expert; allowed: -2..1"
    ):
        make_policy(make_config(tokenizer, grounding_layers=[2]))
    with pytest.raises(
        ValueError, match=r"needs the dataset features \['observation.destination', 'observation.phase'"
    ):
        make_config(tokenizer, labels=("observation.segmentation",)).validate_features()
    cue = make_config(tokenizer, variant="cue", labels=())
    with pytest.raises(
        ValueError, match=r"variant 'cue' .* needs the dataset features \['observation.segmentation'"
    ):
        cue.validate_features()
    assert make_config(tokenizer, variant="plain", labels=()).validate_features() is None
    missing = tmp_path / "no_tokenizer"
    cfg = make_config(tokenizer, tokenizer_name=str(missing))
    cfg.validate_features()
    with pytest.raises(
        ValueError, match=rf"--policy.tokenizer_name='{missing}' cannot be loaded here .* local directory"
    ):
        make_pi05_grounded_pre_post_processors(cfg, stats())


def test_processors_carry_the_plugin_steps_and_reload_by_name(tokenizer, tmp_path):
    cfg = make_config(tokenizer, variant="cue", instruction="explicit")
    cfg.validate_features()
    pre, post = make_pi05_grounded_pre_post_processors(cfg, stats())
    names = [s["registry_name"] for s in pre.get_config()["steps"] if "registry_name" in s]
    assert names[:3] == ["rename_observations_processor", "condground_rgb_cue", "condground_instruction"]
    tokenizer_step = next(
        s for s in pre.get_config()["steps"] if s.get("registry_name") == "tokenizer_processor"
    )
    assert tokenizer_step["config"]["tokenizer_name"] == str(tokenizer)
    out = pre(raw_batch())
    tokens = out["observation.language.tokens"]
    decoded = [pre.steps[-2].input_tokenizer.decode(t, skip_special_tokens=True) for t in tokens]
    assert decoded[0].startswith(f"Task: {instruction('route', 'explicit', 'left')}, State: ")
    assert decoded[1].startswith(f"Task: {instruction('inspect')}, State: ")
    # The cue is drawn on the destination's pixels only.
    top = out["observation.images.top"]
    clean = raw_batch()["observation.images.top"]
    changed = (top - clean).abs().sum(1) > 1e-6
    assert changed[:, 0:12, 0:16].all() and changed.sum() == B * 12 * 16

    pre.save_pretrained(tmp_path)
    post.save_pretrained(tmp_path)
    pre2, _ = make_pre_post_processors(
        cfg, pretrained_path=str(tmp_path), preprocessor_overrides={"device_processor": {"device": "cpu"}}
    )
    again = pre2(raw_batch())
    assert torch.equal(again["observation.language.tokens"], tokens)
    assert torch.equal(again["observation.images.top"], top)


def test_capture_takes_the_action_rows_over_the_image_patches(tokenizer):
    cfg = make_config(tokenizer)
    policy = make_policy(cfg)
    pre, _ = make_pi05_grounded_pre_post_processors(cfg, stats())
    batch = pre(raw_batch())
    n_img = len(CAMERAS) * GRID**2
    full = ExpertAttention({0, 1}, queries=10_000, keys=10_000)  # every row and column
    part = ExpertAttention({1}, queries=CHUNK, keys=n_img)
    policy.train()
    for capture in (full, part):
        torch.manual_seed(0)
        with capture.capturing():
            policy.forward(batch)
    length = n_img + cfg.tokenizer_max_length + CHUNK
    assert [tuple(m.shape) for m in full.maps] == [(B, 8, length, length)] * 2
    assert [tuple(m.shape) for m in part.maps] == [(B, 8, CHUNK, n_img)]
    assert torch.equal(part.maps[0], full.maps[1][:, :, -CHUNK:, :n_img])
    # The image columns are the first n_img: rows sum to 1 over all keys, and a missing camera's
    # patches (the last GRID**2 columns) get exactly no attention.
    no_wrist = {k: v for k, v in batch.items() if k != "observation.images.wrist"}
    capture = ExpertAttention({0}, queries=CHUNK, keys=n_img)
    with capture.capturing():
        policy.forward(no_wrist)
    rows = capture.maps[0]
    assert torch.all(rows[..., GRID**2 :] == 0) and torch.all(rows[..., : GRID**2].sum(-1) > 0)


def test_masks_cover_the_patches_of_their_pixels(tokenizer):
    """48x64 frames are resized to 24x32 and padded by 4 rows above and below (pi05's resize with pad):
    the destination at rows 0-11, columns 0-15 lands on rows 4-9, columns 0-7 of the 32x32 input, which
    are half of patch (0, 0) and a quarter of patch (1, 0)."""
    policy = make_policy(make_config(tokenizer))
    mask = torch.zeros(1, H, W, dtype=torch.bool)
    mask[:, 0:12, 0:16] = True
    grid = pooled_mask(policy._as_model_input(mask), (GRID, GRID))[0]
    assert torch.nonzero(grid).tolist() == [[0, 0], [1, 0]]
    assert grid[0, 0].item() == pytest.approx(1.0) and grid[1, 0].item() == pytest.approx(0.5)


def loss_of(policy, batch, gc: bool, seed=0):
    policy.zero_grad(set_to_none=True)
    (policy.model.gradient_checkpointing_enable if gc else policy.model.gradient_checkpointing_disable)()
    policy.train()
    torch.manual_seed(seed)
    loss, info = policy.forward(batch)
    loss.backward()
    grads = {n: p.grad.clone() for n, p in policy.named_parameters() if p.grad is not None}
    return loss, info, grads


def test_eq1_terms_in_float32_and_their_gradients_with_and_without_checkpointing(tokenizer):
    cfg = make_config(tokenizer, grounding_pos_weight=0.7, grounding_neg_weight=0.3, grounding_heads=[1, 4])
    policy = make_policy(cfg)
    pre, _ = make_pi05_grounded_pre_post_processors(cfg, stats())
    batch = pre(raw_batch())

    loss, info, grads = loss_of(policy, batch, gc=False)
    loss_gc, info_gc, grads_gc = loss_of(policy, batch, gc=True)
    assert loss.dtype == torch.float32 and loss.item() == pytest.approx(loss_gc.item(), rel=1e-6)
    info.pop("loss_per_dim"), info_gc.pop("loss_per_dim")
    assert info == pytest.approx(info_gc, rel=1e-5)
    assert grads.keys() == grads_gc.keys()
    for name in grads:
        torch.testing.assert_close(grads[name], grads_gc[name], rtol=1e-4, atol=1e-7, msg=name)
    expert_q = "model.paligemma_with_expert.gemma_expert.model.layers.1.self_attn.q_proj.weight"
    vision = next(n for n in grads if "vision_tower" in n and "patch_embedding.weight" in n)
    assert grads[expert_q].abs().sum() > 0 and grads[vision].abs().sum() > 0

    # The logged terms, recomputed from the captured attention: sample 0 routes (relevant: destination,
    # distractor: the other container), sample 1 inspects (relevant: the state region, no distractor).
    capture = ExpertAttention({1}, queries=CHUNK, keys=len(CAMERAS) * GRID**2)
    policy.model.gradient_checkpointing_disable()
    torch.manual_seed(0)
    with capture.capturing(), torch.no_grad():
        flow, _ = PI05Policy.forward(policy, batch, reduction="none")
    attention = capture.maps[0][:, [1, 4]].mean(dim=(1, 2))
    seg = batch["observation.segmentation"]
    on_rel, on_dis = [], []
    for j in range(len(CAMERAS)):  # both cameras carry the same labels here
        a = attention[:, j * GRID**2 : (j + 1) * GRID**2]
        a = (a / a.sum(-1, keepdim=True)).view(B, GRID, GRID)
        rel = torch.stack([seg[0] == DESTINATION, seg[1] == STATE_REGION])
        dis = torch.stack([seg[0] == OTHER_CONTAINER, torch.zeros_like(seg[1], dtype=torch.bool)])
        on_rel.append((a * pooled_mask(policy._as_model_input(rel), (GRID, GRID))).sum((1, 2)))
        on_dis.append((a * pooled_mask(policy._as_model_input(dis), (GRID, GRID))).sum((1, 2)))
    on_rel, on_dis = torch.stack(on_rel).mean(0), torch.stack(on_dis).mean(0)
    assert on_dis[1] == 0 and on_rel.min() > 0
    assert info["grounding_on_relevant"] == pytest.approx(on_rel.mean().item(), rel=1e-5)
    assert info["grounding_on_distractors"] == pytest.approx(on_dis.mean().item(), rel=1e-5)
    assert info["flow_loss"] == pytest.approx(flow.mean().item(), rel=1e-5)
    expected = (flow + 0.7 * (1 - on_rel) + 0.3 * on_dis).mean()
    assert loss.item() == pytest.approx(expected.item(), rel=1e-5)

    # Steps without a referent (retreat, home) are not pulled anywhere.
    idle = {**batch, "observation.phase": torch.tensor([[STEPS.index("home")]] * B)}
    _, info_idle, _ = loss_of(policy, idle, gc=False)
    assert info_idle["grounding_supervised_fraction"] == 0 and info_idle["grounding_on_distractors"] == 0
    assert info_idle["loss"] == pytest.approx(info_idle["flow_loss"], rel=1e-6)
    with pytest.raises(ValueError, match=r"grounding loss needs \['observation.phase'\]"):
        policy.forward({k: v for k, v in batch.items() if k != "observation.phase"})


def test_weights_load_strictly_or_not_at_all(tokenizer, tmp_path):
    stock_cfg = make_config(tokenizer, cls=PI05Config, labels=())
    stock = make_policy(stock_cfg, cls=PI05Policy, seed=1)
    stock.save_pretrained(tmp_path / "stock")
    cfg = make_config(tokenizer, variant="plain", labels=())
    with tiny_pi05():
        grounded = PI05GroundedPolicy.from_pretrained(tmp_path / "stock", config=cfg)
    assert grounded.state_dict().keys() == stock.state_dict().keys()
    assert all(torch.equal(v, grounded.state_dict()[k]) for k, v in stock.state_dict().items())

    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "model.safetensors").symlink_to(tmp_path / "nowhere.safetensors")
    with tiny_pi05(), pytest.raises(FileNotFoundError, match="model.safetensors is missing"):
        PI05GroundedPolicy.from_pretrained(broken, config=cfg)
    other = make_config(tokenizer, variant="plain", labels=())
    other.max_action_dim = 16
    with (
        tiny_pi05(),
        pytest.raises(
            ValueError,
            match=r"does not fit pi05_grounded .* 3 of another shape \['model.action_in_proj.weight \(32, 8\) vs \(32, 16\)",
        ),
    ):
        PI05GroundedPolicy.from_pretrained(tmp_path / "stock", config=other)


def test_full_size_has_stock_pi05_names_and_shapes_on_the_meta_device():
    def build(config_cls, policy_cls, **kw):
        cfg = config_cls(device="cpu", **kw)
        cfg.input_features = {c: PolicyFeature(FeatureType.VISUAL, (3, 96, 128)) for c in CAMERAS}
        cfg.input_features["observation.state"] = PolicyFeature(FeatureType.STATE, (7,))
        cfg.output_features = {"action": PolicyFeature(FeatureType.ACTION, (7,))}
        cfg.device = "meta"
        with torch.device("meta"):
            return policy_cls(cfg)

    stock = build(PI05Config, PI05Policy)
    grounded = build(PI05GroundedConfig, PI05GroundedPolicy, variant="plain")
    a, b = stock.state_dict(), grounded.state_dict()
    assert list(b) == list(a) and len(a) == 813
    assert all(b[k].shape == a[k].shape for k in a)
    n_params = sum(p.numel() for p in grounded.parameters())
    assert n_params == sum(p.numel() for p in stock.parameters()) > 4e9


def test_pi05_start_takes_no_tokenizer_path_from_outside_its_source(tokenizer, tmp_path):
    """A source checkpoint's config names what the new tokenizer step loads: a hub id or a path in its folder."""
    from lerobot_condground.policies.pi05_grounded.starting import source_config

    source = tmp_path / "source"
    source.mkdir()
    make_config(tokenizer)._save_pretrained(source)
    with pytest.raises(
        PermissionError, match=rf"{source / 'config.json'}, field 'tokenizer_name', is '{tokenizer}'"
    ):
        source_config(str(source), [])
    assert source_config(str(source), [f"--tokenizer_name={tokenizer}"]).tokenizer_name == str(tokenizer)
    shutil.copytree(tokenizer, source / "tokenizer")
    config = json.loads((source / "config.json").read_text())
    (source / "config.json").write_text(json.dumps({**config, "tokenizer_name": str(source / "tokenizer")}))
    assert source_config(str(source), []).tokenizer_name == str(source / "tokenizer")


def test_pi05_start_that_fails_half_way_leaves_nothing_in_the_way(
    tokenizer, routing_dataset, tmp_path, monkeypatch
):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.processor.pipeline import DataProcessorPipeline

    from lerobot_condground.policies.pi05_grounded.starting import write_starting_checkpoint

    source = tmp_path / "source"
    make_policy(make_config(tokenizer, cls=PI05Config, labels=()), cls=PI05Policy).save_pretrained(source)
    meta = LeRobotDatasetMetadata("local/routing", root=routing_dataset)
    start, overrides = (
        tmp_path / "out" / "start",
        [f"--tokenizer_name={tokenizer}", "--grounding_layers=[0,1]"],
    )

    def disk_full(self, *args, **kwargs):
        raise OSError(28, "No space left on device")

    with tiny_pi05(), monkeypatch.context() as patch:
        patch.setattr(DataProcessorPipeline, "save_pretrained", disk_full)  # config and weights written first
        with pytest.raises(OSError, match="No space left"):
            write_starting_checkpoint(str(source), overrides, meta, start)
    assert list(start.parent.iterdir()) == []
    with tiny_pi05():
        write_starting_checkpoint(str(source), overrides, meta, start)
    assert sorted(p.name for p in start.iterdir())[:2] == ["config.json", "model.safetensors"]


def test_pi05_start_copies_a_local_tokenizer_into_the_checkpoint(
    tokenizer, routing_dataset, tmp_path, monkeypatch
):
    """A tokenizer given by a relative path is copied into the started checkpoint and named there by its
    absolute path (config and tokenizer step), so the checkpoint loads from any folder and passes the
    checkpoint-folder rule of condground's commands; where it came from is recorded."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from transformers import AutoTokenizer

    from lerobot_condground.core.trust import check_name
    from lerobot_condground.policies.pi05_grounded.starting import write_starting_checkpoint

    source = tmp_path / "source"
    make_policy(make_config(tokenizer, cls=PI05Config, labels=()), cls=PI05Policy).save_pretrained(source)
    meta = LeRobotDatasetMetadata("local/routing", root=routing_dataset)
    work = tmp_path / "work" / "here"
    work.mkdir(parents=True)
    monkeypatch.chdir(work)
    relative = Path(os.path.relpath(tokenizer, work))
    with tiny_pi05():
        write_starting_checkpoint(str(source), [f"--tokenizer_name={relative}"], meta, Path("start"))
    start = (work / "start").resolve()
    named = read_json(start / "config.json")["tokenizer_name"]
    step = next(
        s
        for s in read_json(start / "policy_preprocessor.json")["steps"]
        if s["registry_name"] == "tokenizer_processor"
    )
    assert named == step["config"]["tokenizer_name"] == str(start / "tokenizer")
    assert sorted(p.name for p in (start / "tokenizer").iterdir()) == sorted(
        p.name for p in tokenizer.iterdir()
    )
    assert read_json(start / "pi05_start.json")["tokenizer_source"] == str(tokenizer.resolve())
    check_name(start, named, "tokenizer_name")  # inside the checkpoint's folder
    monkeypatch.chdir(tmp_path)
    assert (
        AutoTokenizer.from_pretrained(named)("pick").input_ids
        == AutoTokenizer.from_pretrained(tokenizer)("pick").input_ids
    )


def test_pi05_start_then_stock_lerobot_train(tokenizer, routing_dataset, tmp_path, monkeypatch):
    tests = Path(__file__).parents[1]
    monkeypatch.setenv("PYTHONPATH", f"{tests / 'pi05_site'}:{tests}")
    monkeypatch.setenv("CONDGROUND_TINY_PI05", "1")
    source = tmp_path / "pi05_source"
    make_policy(make_config(tokenizer, cls=PI05Config, labels=()), cls=PI05Policy).save_pretrained(source)
    # Offline, the tokenizer and the weights come from the hub cache by hub id (the layout `hf download`
    # leaves): a checkpoint naming a tokenizer directory outside its folder is refused by our commands.
    cache = tmp_path / "hub"
    monkeypatch.setenv("HF_HUB_CACHE", str(cache))
    tokenizer_repo = cache_repo(cache, "local/tokenizer", tokenizer)
    (tokenizer_repo / "config.json").write_text('{"model_type": "gemma"}')  # as in google/paligemma-3b-pt-224

    start = tmp_path / "start"
    flags = [
        f"--policy.path={source}", "--dataset.repo_id=local/routing", f"--dataset.root={routing_dataset}",
        "--policy.tokenizer_name=local/tokenizer", "--policy.grounding_layers=[0,1]",
    ]  # fmt: skip
    out = run_cli("condground", "pi05-start", *flags, f"--output_dir={start}")
    assert "Fine-tune with:" in out.stdout
    config = read_json(start / "config.json")
    assert config["type"] == "pi05_grounded" and config["variant"] == "regularized"
    assert set(config["input_features"]) == {*CAMERAS, "observation.state"}
    assert set(config["label_keys"]) == set(LABELS)
    assert (start / "model.safetensors").resolve() == (source / "model.safetensors").resolve()
    steps = [s["registry_name"] for s in read_json(start / "policy_preprocessor.json")["steps"]]
    assert steps[1:3] == ["condground_decode_labels", "condground_instruction"]

    # A hub id resolves offline from the local cache, as pi05_base would.
    snapshot = cache_repo(cache, "local/pi05_tiny", source)
    from_hub = tmp_path / "start_from_hub"
    run_cli(
        "condground", "pi05-start", "--policy.path=local/pi05_tiny", *flags[1:], f"--output_dir={from_hub}"
    )
    assert (from_hub / "model.safetensors").resolve() == (snapshot / "model.safetensors").resolve()
    missing = run_cli("condground", "pi05-start", "--policy.path=local/absent", *flags[1:], f"--output_dir={tmp_path / 'y'}", check=False)  # fmt: skip
    assert missing.returncode == 2 and "'local/absent' is not a checkpoint directory" in missing.stderr

    again = run_cli("condground", "pi05-start", *flags, f"--output_dir={start}", check=False)
    assert again.returncode == 2 and "exists and is not empty" in again.stderr
    wrong = run_cli("condground", "pi05-start", *flags[:-1], "--policy.max_action_dim=16", f"--output_dir={tmp_path / 'x'}", check=False)  # fmt: skip
    assert wrong.returncode == 2 and "does not fit pi05_grounded" in wrong.stderr
    assert not (tmp_path / "x").exists()

    train = tmp_path / "train"
    run_cli(
        "lerobot-train", f"--policy.path={start}", "--policy.push_to_hub=false", "--policy.device=cpu",
        "--dataset.repo_id=local/routing", f"--dataset.root={routing_dataset}", "--batch_size=2", "--steps=2",
        "--save_freq=2", "--log_freq=1", "--num_workers=0", f"--output_dir={train}", "--wandb.enable=false",
    )  # fmt: skip
    checkpoint = train / "checkpoints" / "last" / "pretrained_model"
    saved = [s["registry_name"] for s in read_json(checkpoint / "policy_preprocessor.json")["steps"]]
    assert saved == steps
    assert read_json(checkpoint / "config.json")["grounding_layers"] == [0, 1]
    with tiny_pi05():
        trained = PI05GroundedPolicy.from_pretrained(checkpoint)
    assert json.loads((checkpoint / "config.json").read_text())["type"] == trained.name

    # The trained checkpoint through `condground subgoals` (regularized: clean frames, explicit text).
    subgoals = tmp_path / "subgoals"
    out = run_cli(
        "condground", "subgoals", f"--policy.path={checkpoint}", "--env.task=InstrumentRouting-v0",
        "--condition=explicit", "--trials=1", "--subgoals=route,place", "--max_steps=3", "--policy.device=cpu",
        f"--output_dir={subgoals}", "--progress=false",
    )  # fmt: skip
    assert "| route (routing) |" in out.stdout
    rows = pd.read_parquet(subgoals / "results.parquet")
    assert sorted(rows["subgoal"]) == ["place", "route"] and set(rows["policy_type"]) == {"pi05_grounded"}
    assert set(rows["steps"]) <= {3} and not rows["success"].any()


@pytest.mark.parametrize("mode", ["train_expert_only", "freeze_vision_encoder", "peft"])
def test_regularizer_trains_with_pi05s_partial_fine_tuning(tokenizer, mode):
    import dataclasses

    from lerobot.configs.default import PeftConfig

    cfg = make_config(tokenizer, **({mode: True} if mode != "peft" else {}))
    policy = make_policy(cfg)
    pre, _ = make_pi05_grounded_pre_post_processors(cfg, stats())
    batch = pre(raw_batch())
    if mode == "peft":
        cfg.pretrained_path = "pi05_base"  # LeRobot refuses adapters on a policy trained from scratch
        policy = policy.wrap_with_peft(peft_cli_overrides=dataclasses.asdict(PeftConfig(r=4)))
    policy.train()
    loss, info = policy.forward(batch)
    loss.backward()
    assert 0 < info["grounding_on_relevant"] < 1
    grads = {n: p.grad for n, p in policy.named_parameters() if p.requires_grad and p.grad is not None}
    frozen = [n for n, p in policy.named_parameters() if not p.requires_grad]
    # LoRA's B starts at zero, so only B has a gradient at first.
    expert_q = [g for n, g in grads.items() if "gemma_expert" in n and "q_proj" in n and "lora_A" not in n]
    assert frozen and expert_q and all(g.abs().sum() > 0 for g in expert_q)
    if mode == "train_expert_only":
        assert not any("paligemma.model" in n for n in grads)
    elif mode == "freeze_vision_encoder":
        assert not any("vision_tower" in n for n in grads)
        assert any("language_model" in n and "q_proj" in n for n in grads)
    else:
        assert any("lora_" in n for n in grads) and all("lora_" in n or "proj" in n for n in grads)


def test_pi05_bench_times_every_setting(capsys):
    from lerobot_condground.bench.pi05 import SETTINGS, Pi05BenchConfig, bench_pi05
    from lerobot_condground.cli import main

    cfg = Pi05BenchConfig(
        device="cpu", dtype="float32", batch_sizes=[2], steps=1, rounds=2, image_size=48,
        image_resolution=RES, chunk_size=CHUNK, tokens=16,
    )  # fmt: skip
    with tiny_pi05():
        results = bench_pi05(cfg)
    assert results["device"] == "cpu" and 0 < results["parameters"] < 1e6
    for name in SETTINGS:
        assert results[f"b2_{name}_step_s"] > 0
    assert all(results[f"b2_{name}_step_ratio"] > 0 for name in SETTINGS if name != "plain")
    assert results["select_action_s"] > 0
    assert main(["pi05-bench", "--batch_sizes=[8,0]"]) == 2
    assert "--batch_sizes=[8, 0] is not allowed" in capsys.readouterr().err


def test_pi05_start_names_a_weights_file_with_a_crafted_header(tokenizer, tmp_path):
    """A header claiming 2^62 bytes is refused in one line naming the file, before any policy is built."""
    from lerobot_condground.policies.pi05_grounded.starting import check_weights

    weights = tmp_path / "model.safetensors"
    weights.write_bytes((2**62).to_bytes(8, "little") + b"{}")
    with pytest.raises(ValueError, match=f"{weights} is not a readable safetensors file"):
        check_weights(make_config(tokenizer), weights)
