"""The act_modified policy on small CPU configs: variants, equality with stock ACT, the attention
loss, prompt selection, checkpoints and warm starts."""

import copy
import json

import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.policies.act.modeling_act import ACTPolicy

from lerobot_condground.core.labels import (
    OBS_PHASE,
    OBS_PROMPT_OBJECT,
    OBS_PROMPT_RECEPTACLE,
    OBS_SEGMENTATION,
    TARGET_OBJECT,
    TARGET_RECEPTACLE,
)
from lerobot_condground.policies.act_modified.configuration_act_modified import VARIANTS, ACTModifiedConfig
from lerobot_condground.policies.act_modified.modeling_act_modified import (
    ACTModifiedPolicy,
    attention_overlaps,
    grid_attention,
    prompt_as_image,
)

H, W, B, CHUNK = 64, 96, 4, 5
CAMERA = "observation.images.top"
SMALL = dict(
    dim_model=32,
    n_heads=4,
    dim_feedforward=64,
    n_encoder_layers=1,
    n_vae_encoder_layers=1,
    chunk_size=CHUNK,
    n_action_steps=CHUNK,
    pretrained_backbone_weights=None,
    device="cpu",
)
ACTION_FEATURES = {"action": PolicyFeature(FeatureType.ACTION, (7,))}


def dataset_features(labels: bool = True) -> dict:
    features = {
        CAMERA: PolicyFeature(FeatureType.VISUAL, (3, H, W)),
        "observation.state": PolicyFeature(FeatureType.STATE, (7,)),
    }
    if labels:
        features |= {
            OBS_SEGMENTATION: PolicyFeature(FeatureType.STATE, (H, W)),
            OBS_PHASE: PolicyFeature(FeatureType.STATE, (1,)),
            OBS_PROMPT_OBJECT: PolicyFeature(FeatureType.STATE, (64, 64, 3)),
            OBS_PROMPT_RECEPTACLE: PolicyFeature(FeatureType.STATE, (64, 64, 3)),
        }
    return features


def make_policy(**overrides) -> ACTModifiedPolicy:
    torch.manual_seed(0)
    cfg = ACTModifiedConfig(
        input_features=dataset_features(), output_features=dict(ACTION_FEATURES), **SMALL | overrides
    )
    return ACTModifiedPolicy(cfg)


def make_batch(seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    seg = torch.zeros(B, H, W, dtype=torch.long)
    seg[:, 8:24, 8:24] = TARGET_OBJECT
    seg[:, 32:56, 56:88] = TARGET_RECEPTACLE
    seg[:, 40:56, 8:24] = 3  # a real competitor
    return {
        CAMERA: torch.rand(B, 3, H, W, generator=g),
        "observation.state": torch.randn(B, 7, generator=g),
        "action": torch.randn(B, CHUNK, 7, generator=g),
        "action_is_pad": torch.zeros(B, CHUNK, dtype=torch.bool),
        OBS_SEGMENTATION: seg,
        OBS_PHASE: torch.tensor([0, 1] * (B // 2)),
        OBS_PROMPT_OBJECT: torch.randint(0, 256, (B, 64, 64, 3), generator=g),
        OBS_PROMPT_RECEPTACLE: torch.randint(0, 256, (B, 64, 64, 3), generator=g),
    }


def observation(batch: dict) -> dict:
    return {
        k: v for k, v in batch.items() if k not in ("action", "action_is_pad", OBS_SEGMENTATION, OBS_PHASE)
    }


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_every_variant_trains_and_acts(variant):
    policy = make_policy(variant=variant)
    assert set(policy.config.input_features) == {CAMERA, "observation.state"}, "labels must never be inputs"
    policy.train()
    loss, info = policy(make_batch())
    loss.backward()
    assert torch.isfinite(loss)
    grads = {n: p.grad for n, p in policy.named_parameters() if p.requires_grad}
    assert all(g is not None and torch.isfinite(g).all() for g in grads.values()), [
        n for n, g in grads.items() if g is None
    ]
    expected = {"l1_loss", "kld_loss"}
    if variant in ("augmentation_attention", "full"):
        expected |= {"attention_on_relevant", "attention_on_distractors"}
    if VARIANTS[variant]["use_phase_predictor"]:
        expected |= {"phase_loss", "phase_accuracy"}
    assert set(info) == expected
    policy.reset()
    action = policy.select_action(observation(make_batch(1)))
    assert action.shape == (B, 7) and torch.isfinite(action).all()


def test_standard_variant_is_stock_act():
    act = ACTPolicy(
        ACTConfig(
            input_features=dataset_features(labels=False), output_features=dict(ACTION_FEATURES), **SMALL
        )
    )
    ours = make_policy(variant="standard")
    assert ours.load_state_dict(act.state_dict(), strict=True)
    batch = make_batch()
    for policy in (act, ours):
        policy.eval()
    torch.testing.assert_close(
        ours.predict_action_chunk(observation(batch)),
        act.predict_action_chunk(observation(batch)),
        rtol=0,
        atol=0,
    )
    act.train()
    ours.train()
    torch.manual_seed(3)
    act_loss, _ = act(batch)
    torch.manual_seed(3)
    our_loss, _ = ours(batch)
    assert our_loss.item() == act_loss.item()


@pytest.mark.parametrize(
    "norm, layer", [("batchnorm", torch.nn.BatchNorm2d), ("groupnorm", torch.nn.GroupNorm)]
)
def test_backbone_norm_trains_where_frozen_batch_norm_is_an_identity(norm, layer):
    """From scratch, ACT's frozen batch norm normalizes nothing; the option puts norm layers that learn in
    every place ResNet has one, and a training step reaches them."""
    frozen = make_policy(variant="standard").model.backbone
    policy = make_policy(variant="standard", backbone_norm=norm)
    norms = [m for m in policy.model.backbone.modules() if isinstance(m, layer)]
    assert len(norms) == sum(type(m).__name__ == "FrozenBatchNorm2d" for m in frozen.modules()) > 0
    policy.train()
    loss, _ = policy(make_batch())
    loss.backward()
    assert all(m.weight.grad is not None and m.weight.grad.abs().sum() > 0 for m in norms)
    policy.eval()
    action = policy.select_action(observation(make_batch(1)))
    assert torch.isfinite(action).all()


def test_prompt_crops_leave_the_scene_batch_norm_statistics_alone():
    """Training encodes the crops with the running statistics, as inference does, and does not move them:
    after a training forward they are what the scene images alone make of them."""
    policy = make_policy(variant="full", backbone_norm="batchnorm", backbone_width=32)
    policy.train()
    model = policy.model
    scene_only = copy.deepcopy(model.backbone)
    batch = make_batch()
    with torch.no_grad():
        policy(batch)
        scene_only(batch[CAMERA])
    norms = [(a, b) for a, b in zip(model.backbone.modules(), scene_only.modules(), strict=True)]
    norms = [(a, b) for a, b in norms if isinstance(a, torch.nn.BatchNorm2d)]
    assert norms and all(
        torch.allclose(a.running_mean, b.running_mean) and torch.allclose(a.running_var, b.running_var)
        for a, b in norms
    )
    crops = prompt_as_image(make_batch(2)[OBS_PROMPT_OBJECT][:2])
    in_training = model._encode_prompts(crops)
    assert all(a.training for a, _ in norms)  # back in training mode for the scene
    model.eval()
    assert torch.allclose(in_training, model._encode_prompts(crops), atol=1e-6)


@pytest.mark.parametrize("variant", ["standard", "full"])
def test_narrow_backbone_halves_every_stage_and_trains(variant):
    """backbone_width=32: ResNet-18's layout at half the channels, its feature map projected like ACT's,
    trained end to end (the phase head and prompt encoder read the narrower features too)."""
    wide = make_policy(variant=variant, backbone_norm="batchnorm")
    policy = make_policy(variant=variant, backbone_norm="batchnorm", backbone_width=32)
    feature_map = policy.model.backbone(torch.rand(B, 3, H, W))["feature_map"]
    assert feature_map.shape[1] == 256 == policy.model.encoder_img_feat_input_proj.in_channels
    assert feature_map.shape[2:] == wide.model.backbone(torch.rand(B, 3, H, W))["feature_map"].shape[2:]
    count = lambda m: sum(p.numel() for p in m.backbone.parameters())  # noqa: E731
    assert 0.2 < count(policy.model) / count(wide.model) < 0.3
    policy.train()
    loss, _ = policy(make_batch())
    loss.backward()
    assert policy.model.backbone.conv1.weight.grad.abs().sum() > 0
    policy.eval()
    assert torch.isfinite(policy.select_action(observation(make_batch(1)))).all()


def test_narrow_backbone_takes_the_final_dilation():
    """replace_final_stride_with_dilation on the narrow ResNet doubles the feature map's sides (stride 16)
    instead of being ignored, and the attention terms pool their masks onto that finer grid."""
    coarse = make_policy(variant="full", backbone_norm="batchnorm", backbone_width=32)
    fine = make_policy(
        variant="full", backbone_norm="batchnorm", backbone_width=32, replace_final_stride_with_dilation=True
    )
    image = torch.rand(B, 3, H, W)
    coarse_hw = coarse.model.backbone(image)["feature_map"].shape[2:]
    assert fine.model.backbone(image)["feature_map"].shape[2:] == (2 * coarse_hw[0], 2 * coarse_hw[1])
    fine.train()
    loss, terms = fine(make_batch())
    loss.backward()
    assert torch.isfinite(loss) and terms["attention_on_relevant"] > 0
    assert fine.model.backbone.conv1.weight.grad.abs().sum() > 0


@pytest.mark.parametrize("width", [64, 16])
def test_backbone_cut_after_layer3_doubles_the_token_grid_without_layer4(width):
    """backbone_layer=layer3: stride 16 (twice the grid's sides) from the stage before layer4, whose weights
    are not even built; the projection takes that stage's channels and the attention terms pool onto the grid."""
    settings = dict(variant="full", backbone_norm="batchnorm", backbone_width=width)
    coarse, fine = make_policy(**settings), make_policy(**settings, backbone_layer="layer3")
    image = torch.rand(B, 3, H, W)
    coarse_map, fine_map = (
        coarse.model.backbone(image)["feature_map"],
        fine.model.backbone(image)["feature_map"],
    )
    assert fine_map.shape[2:] == (2 * coarse_map.shape[2], 2 * coarse_map.shape[3])
    assert fine_map.shape[1] * 2 == coarse_map.shape[1] == 8 * width
    assert fine.model.encoder_img_feat_input_proj.in_channels == 4 * width
    assert not any(name.startswith("layer4") for name, _ in fine.model.backbone.named_parameters())
    fine.train()
    loss, terms = fine(make_batch())
    loss.backward()
    assert torch.isfinite(loss) and terms["attention_on_relevant"] > 0
    assert fine.model.backbone.conv1.weight.grad.abs().sum() > 0
    fine.eval()
    assert torch.isfinite(fine.select_action(observation(make_batch(1)))).all()


def test_every_loss_term_holds_under_bf16_autocast():
    """lerobot-train --policy.use_amp=true runs forward under bf16 autocast: the recomputed attention softmax,
    the phase cross-entropy, the attention terms and the prompt encoding must stay within bf16 rounding of
    fp32 (dropout off, so both passes compute the same function)."""
    policy = make_policy(
        variant="full", use_phase_predictor=True, dropout=0.0, backbone_norm="batchnorm", backbone_width=32
    )
    policy.train()
    batch = make_batch()
    torch.manual_seed(1)  # the same CVAE sample in both passes
    _, fp32 = policy(batch)
    torch.manual_seed(1)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss, bf16 = policy(batch)
    assert loss.dtype == torch.float32 and torch.isfinite(loss)
    assert (
        fp32.keys()
        == bf16.keys()
        >= {"l1_loss", "phase_loss", "attention_on_relevant", "attention_on_distractors"}
    )
    for key in fp32:
        assert bf16[key] == pytest.approx(fp32[key], rel=0.05, abs=0.01), key


def test_channels_last_computes_the_same_function_and_checkpoints_as_lerobot_does(tmp_path):
    """--policy.channels_last is a speed setting: the backbone's activations are channels-last, the loss and
    gradients agree with the default memory order to float rounding, and LeRobot's checkpoint writers take the
    weights and AdamW's state (safetensors refuses non-contiguous tensors)."""
    from lerobot.optim.optimizers import save_optimizer_state

    batch = make_batch()
    losses, grads, maps = [], [], []
    for channels_last in (False, True):
        policy = make_policy(
            variant="full", dropout=0.0, backbone_norm="batchnorm", channels_last=channels_last
        )
        policy.model.backbone.register_forward_hook(lambda m, a, out: maps.append(out["feature_map"]))
        policy.train()
        torch.manual_seed(1)
        loss, _ = policy(batch)
        loss.backward()
        losses.append(loss.item())
        grads.append(torch.cat([p.grad.flatten() for p in policy.parameters() if p.grad is not None]))
    assert maps[0].is_contiguous() and not maps[-1].is_contiguous()
    assert maps[-1].is_contiguous(memory_format=torch.channels_last)
    assert losses[1] == pytest.approx(losses[0], rel=1e-4)
    assert torch.allclose(grads[1], grads[0], rtol=1e-3, atol=1e-5)
    optimizer = torch.optim.AdamW(policy.parameters())
    optimizer.step()
    (tmp_path / "optimizer").mkdir()
    save_optimizer_state(optimizer, tmp_path / "optimizer")
    policy.save_pretrained(tmp_path / "policy")
    loaded = ACTModifiedPolicy.from_pretrained(tmp_path / "policy")
    for (name, a), b in zip(policy.state_dict().items(), loaded.state_dict().values(), strict=True):
        assert torch.equal(a, b), name


def test_cpu_training_configuration_parses_as_lerobot_train_flags():
    """The flags the quickstart and the learning-curve script hand to lerobot-train build a valid policy."""
    import draccus

    from lerobot_condground.core.training import CPU_POLICY, policy_flags

    args = [flag.removeprefix("--policy.") for flag in policy_flags()]
    cfg = draccus.parse(ACTModifiedConfig, args=[f"--{a}" for a in args])
    assert {key: getattr(cfg, key) for key in CPU_POLICY} == CPU_POLICY


def test_supervised_head_attention_is_the_heads_softmax():
    policy = make_policy(variant="augmentation_attention", attention_head=2)
    policy.eval()
    mha = policy.model.decoder.layers[-1].multihead_attn
    query, key = torch.randn(CHUNK, B, 32), torch.randn(20, B, 32)
    mha.capture = True
    _, weights = mha(query, key, key, need_weights=True, average_attn_weights=False)
    mha.capture = False
    torch.testing.assert_close(mha.head_log_attention(2).exp(), weights[:, 2])


def test_grid_attention_is_the_renormalized_camera_attention_even_where_the_camera_gets_almost_none():
    logits = torch.randn(B, CHUNK, 20)
    camera = slice(8, 20)
    attention = logits.softmax(-1)[:, :, camera].mean(1)
    torch.testing.assert_close(
        grid_attention(logits.log_softmax(-1)[:, :, camera]), attention / attention.sum(-1, keepdim=True)
    )
    # A head whose mass sits on the 1D tokens: the camera's share rounds to 0 and the plain ratio is 0/0.
    logits[:, :, :8] += 200.0
    log_attention = logits.log_softmax(-1)[:, :, camera]
    assert log_attention.exp().sum(-1).eq(0).all()
    expected = logits.double().softmax(-1)[:, :, camera].mean(1)  # the ratio where float64 does not underflow
    torch.testing.assert_close(
        grid_attention(log_attention), (expected / expected.sum(-1, keepdim=True)).float()
    )


def test_a_non_finite_loss_stops_training_before_the_weights_are_touched():
    policy = make_policy(variant="full")
    policy.train()
    batch = make_batch()
    batch["action"][0, 0, 0] = float("nan")
    with pytest.raises(FloatingPointError, match=r"loss is not finite \(l1_loss=nan"):
        policy(batch)


def test_attention_loss_moves_attention_to_the_relevant_mask():
    policy = make_policy(variant="augmentation_attention", attention_pos_weight=5.0, attention_neg_weight=5.0)
    batch = make_batch()
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-3)

    def overlaps():
        policy.eval()
        with torch.no_grad():
            aux = policy.model(policy._images_listed(batch), with_attention=True)[2]
        return [
            o.mean().item()
            for o in attention_overlaps(aux["attention"], batch[OBS_SEGMENTATION], batch[OBS_PHASE])
        ]

    relevant_before, distractors_before = overlaps()
    policy.train()
    for _ in range(40):
        optimizer.zero_grad()
        policy(batch)[0].backward()
        optimizer.step()
    relevant_after, distractors_after = overlaps()
    assert relevant_after > relevant_before + 0.3, (relevant_before, relevant_after)
    assert distractors_after < distractors_before, (distractors_before, distractors_after)


def test_memory_normalization_supervises_the_heads_own_attention_on_the_camera():
    """With attention_normalization=memory, A is the head's attention on the grid as a share of the whole memory
    (latent, state, camera tokens): the same map as the camera normalization's, scaled by the camera's share."""
    batch = make_batch()
    maps = {}
    for normalization in ("camera", "memory"):
        policy = make_policy(variant="augmentation_attention", attention_normalization=normalization)
        policy.eval()
        with torch.no_grad():
            maps[normalization] = policy.model(policy._images_listed(batch), with_attention=True)[2][
                "attention"
            ]
    share = maps["memory"].sum(dim=(1, 2))
    assert (share > 0).all() and (share < 1 - 1e-3).all(), share  # two 1D tokens hold part of the mass
    torch.testing.assert_close(maps["memory"] / share.view(-1, 1, 1), maps["camera"])
    on_relevant = {
        k: attention_overlaps(v, batch[OBS_SEGMENTATION], batch[OBS_PHASE])[0] for k, v in maps.items()
    }
    torch.testing.assert_close(on_relevant["memory"], on_relevant["camera"] * share)
    with pytest.raises(
        ValueError, match="attention_normalization='grid' is not allowed; allowed: camera, memory"
    ):
        make_policy(attention_normalization="grid")


@pytest.mark.parametrize("detach", [False, True])
def test_phase_head_detach_keeps_the_phase_loss_out_of_the_backbone(detach):
    """phase_head_detach=true: L_phi trains the phase head only; the backbone it reads gets none of its gradient
    (without it, L_phi reaches the backbone)."""
    policy = make_policy(variant="augmentation", use_phase_predictor=True, phase_head_detach=detach)
    policy.train()
    batch = make_batch()
    aux = policy.model(policy._images_listed(batch))[2]
    torch.nn.functional.cross_entropy(aux["phase_logits"], batch[OBS_PHASE]).backward()
    backbone = sum(
        p.grad.abs().sum().item() for p in policy.model.backbone.parameters() if p.grad is not None
    )
    head = sum(p.grad.abs().sum().item() for p in policy.model.phase_head.parameters())
    assert head > 0
    assert (backbone == 0) if detach else (backbone > 0), backbone


def test_empty_masks_give_a_finite_loss():
    policy = make_policy(variant="augmentation_attention")
    batch = make_batch()
    batch[OBS_SEGMENTATION] = torch.zeros_like(batch[OBS_SEGMENTATION])  # target occluded, no distractors
    policy.train()
    loss, info = policy(batch)
    loss.backward()
    assert (
        torch.isfinite(loss)
        and info["attention_on_relevant"] == 0.0
        and info["attention_on_distractors"] == 0.0
    )
    assert all(torch.isfinite(p.grad).all() for p in policy.parameters() if p.grad is not None)


def test_predicted_phase_picks_the_prompt_at_inference():
    policy = make_policy(variant="full", use_phase_predictor=True)
    policy.eval()
    head = policy.model.phase_head[-1]
    batch = observation(make_batch())
    other = torch.zeros_like(batch[OBS_PROMPT_OBJECT])
    for phase, fed, ignored in (
        (0, OBS_PROMPT_OBJECT, OBS_PROMPT_RECEPTACLE),
        (1, OBS_PROMPT_RECEPTACLE, OBS_PROMPT_OBJECT),
    ):
        with torch.no_grad():
            head.bias.copy_(torch.tensor([10.0, -10.0]) if phase == 0 else torch.tensor([-10.0, 10.0]))
            head.weight.zero_()
        reference = policy.predict_action_chunk(batch)
        assert torch.equal(policy.predict_action_chunk(batch | {ignored: other}), reference)
        assert not torch.allclose(policy.predict_action_chunk(batch | {fed: other}), reference)


@pytest.mark.parametrize("phase_predictor", [False, True])
def test_both_prompts_are_fed_whatever_the_phase(phase_predictor):
    """prompt_selection=both: the memory holds both crops' tokens in training and at inference, so each crop
    moves the action and no phase (label or prediction) decides which one is seen; no phase head is needed."""
    policy = make_policy(variant="full", prompt_selection="both", use_phase_predictor=phase_predictor)
    assert hasattr(policy.model, "phase_head") == phase_predictor
    policy.train()
    batch = make_batch()
    loss, info = policy(batch)
    loss.backward()
    assert torch.isfinite(loss) and ("phase_loss" in info) == phase_predictor
    assert policy.model.prompt_pos_embed.weight.grad.abs().sum(-1).gt(0).all(), "both prompt positions train"
    policy.eval()
    obs = observation(batch)
    reference = policy.predict_action_chunk(obs)
    for key in (OBS_PROMPT_OBJECT, OBS_PROMPT_RECEPTACLE):
        changed = policy.predict_action_chunk(obs | {key: torch.zeros_like(obs[key])})
        assert not torch.allclose(changed, reference), f"{key} is not read"
    if phase_predictor:  # the head's prediction no longer picks a crop
        head = policy.model.phase_head[-1]
        with torch.no_grad():
            head.weight.zero_()
            head.bias.copy_(torch.tensor([-10.0, 10.0]))
        assert torch.equal(policy.predict_action_chunk(obs), reference)


def test_missing_labels_name_the_keys_and_a_variant_that_works():
    features = dataset_features()
    del features[OBS_PROMPT_OBJECT], features[OBS_PROMPT_RECEPTACLE]
    cfg = ACTModifiedConfig(
        variant="full", input_features=features, output_features=dict(ACTION_FEATURES), **SMALL
    )
    with pytest.raises(
        ValueError, match=r"prompt\.object.*prompt\.receptacle.*--policy\.variant=augmentation_attention"
    ):
        ACTModifiedPolicy(cfg)
    cfg = ACTModifiedConfig(
        variant="augmentation",
        input_features=dataset_features(labels=False),
        output_features=dict(ACTION_FEATURES),
        **SMALL,
    )
    with pytest.raises(ValueError, match=r"segmentation.*--policy\.variant=standard builds"):
        ACTModifiedPolicy(cfg)


@pytest.mark.parametrize(
    "overrides, message",
    [
        (dict(variant="best"), "variant 'best'"),
        (dict(attention_head=4), "attention_head=4"),
        (dict(variant="standard", use_prompts=True, prompt_selection="phase"), "use_phase_predictor"),
        (dict(prompt_selection="random"), "prompt_selection='random'.*phase, both"),
        (dict(attention_neg_weight=-1.0), "attention_neg_weight=-1.0"),
        (dict(copy_paste_prob=1.5), "1.5"),
        (dict(copy_paste_warmup_steps=-1), "warmup_steps=-1.*an integer"),
        (
            dict(copy_paste_categories=["same_color", "lookalike"]),
            r"categories=\['same_color', 'lookalike'\]",
        ),
        (dict(backbone_norm="layernorm"), "backbone_norm='layernorm'"),
        (dict(backbone_layer="layer2"), "backbone_layer='layer2'.*layer4, layer3"),
        (
            dict(backbone_layer="layer3", backbone_norm="batchnorm", replace_final_stride_with_dilation=True),
            "one of the two",
        ),
        (dict(scheduler_name="linear"), "scheduler_name='linear'.*constant, cosine"),
        (dict(scheduler_warmup_steps=-1), "scheduler_warmup_steps=-1"),
        (dict(ema_decay=1.0), r"ema_decay=1.0 must be in \(0, 1\)"),
        (
            dict(backbone_norm="groupnorm", pretrained_backbone_weights="ResNet18_Weights.IMAGENET1K_V1"),
            "groupnorm",
        ),
        (dict(backbone_width=20, backbone_norm="batchnorm"), "backbone_width=20"),
        (dict(backbone_width=32), "frozen batch norm normalizes nothing"),
        (dict(backbone_width=32, backbone_norm="batchnorm", vision_backbone="resnet50"), "resnet50"),
        (dict(backbone_width=48, backbone_norm="groupnorm"), "multiple of 32"),
        (
            dict(
                backbone_width=32,
                backbone_norm="batchnorm",
                pretrained_backbone_weights="ResNet18_Weights.IMAGENET1K_V1",
            ),
            "set it to null",
        ),
    ],
)
def test_bad_settings_fail_at_parse_time(overrides, message):
    with pytest.raises(ValueError, match=message):
        ACTModifiedConfig(**SMALL | overrides)


def test_variant_presets_can_be_overridden():
    cfg = ACTModifiedConfig(variant="full", use_copy_paste=False, **SMALL)
    assert (cfg.use_copy_paste, cfg.use_attention_loss, cfg.use_prompts, cfg.use_phase_predictor) == (
        False,
        True,
        True,
        False,
    )


@pytest.mark.parametrize(
    "overrides, selection",
    [
        (dict(), "both"),  # full's settled default: both crops, no phase predictor
        (dict(use_phase_predictor=True), "phase"),  # the paper's: the predictor picks the crop
        (dict(use_phase_predictor=True, prompt_selection="both"), "both"),
        (dict(variant="augmentation", use_phase_predictor=True), "phase"),
    ],
)
def test_prompt_selection_follows_the_phase_predictor_unless_given(overrides, selection):
    assert ACTModifiedConfig(**SMALL | overrides).prompt_selection == selection


@pytest.mark.parametrize("variant", ["augmentation", "augmentation_attention", "full"])
def test_pastes_ramp_in_by_default(variant):
    """A from-scratch backbone fed pastes from the first batch never found the cube on Task 2: by default the
    first training batch is pasted on with probability 0, and the ramp can be switched off."""
    config = ACTModifiedConfig(variant=variant, **SMALL)
    step = config.make_copy_paste_step()
    assert (step.warmup_steps, step.current_prob()) == (3000, 0.0)
    assert (
        ACTModifiedConfig(variant=variant, copy_paste_warmup_steps=0, **SMALL)
        .make_copy_paste_step()
        .current_prob()
        == config.copy_paste_prob
    )


def test_a_checkpoint_saved_before_prompt_selection_loads_as_it_was_trained(tmp_path):
    """Configs written before the field existed hold a phase predictor and no prompt_selection: they must
    load with the predictor picking the crop, as they were trained, not with the later default."""
    policy = make_policy(variant="full", use_phase_predictor=True)
    policy.save_pretrained(tmp_path)
    config = json.loads((tmp_path / "config.json").read_text())
    assert config.pop("prompt_selection") == "phase"
    (tmp_path / "config.json").write_text(json.dumps(config))
    loaded = ACTModifiedPolicy.from_pretrained(tmp_path)
    assert loaded.config.prompt_selection == "phase" and hasattr(loaded.model, "phase_head")
    assert torch.equal(loaded.model.prompt_pos_embed.weight, policy.model.prompt_pos_embed.weight)


def test_checkpoint_round_trip_gives_identical_actions(tmp_path):
    from lerobot.policies.factory import make_pre_post_processors

    policy = make_policy(variant="full")
    stats = {
        CAMERA: {"mean": torch.full((3, 1, 1), 0.4), "std": torch.full((3, 1, 1), 0.2)},
        "observation.state": {"mean": torch.zeros(7), "std": torch.ones(7)},
        "action": {"mean": torch.ones(7), "std": torch.full((7,), 2.0)},
    }
    preprocessor, postprocessor = make_pre_post_processors(policy.config, dataset_stats=stats)
    for part in (policy, preprocessor, postprocessor):
        part.save_pretrained(tmp_path)
    loaded = ACTModifiedPolicy.from_pretrained(tmp_path)
    loaded_pre, loaded_post = make_pre_post_processors(loaded.config, pretrained_path=str(tmp_path))
    assert loaded.config.variant == "full" and loaded.config.label_keys == policy.config.label_keys
    assert [type(s) for s in loaded_pre.steps] == [type(s) for s in preprocessor.steps]

    def act(policy, pre, post):
        policy.reset()
        return post(policy.select_action(pre(observation(make_batch()))))

    torch.testing.assert_close(
        act(loaded, loaded_pre, loaded_post), act(policy, preprocessor, postprocessor), rtol=0, atol=0
    )


def test_moving_average_trails_the_weights_acts_and_survives_a_checkpoint(tmp_path):
    policy = make_policy(variant="standard", ema_decay=0.5)
    optimizer = torch.optim.AdamW(
        [g for group in policy.get_optim_params() for g in group["params"]], lr=1e-2
    )
    assert not any(p is e for p in optimizer.param_groups[0]["params"] for e in policy.ema_model.parameters())
    raw, ema = (
        policy.model.vae_encoder_action_input_proj.weight,
        policy.ema_model.vae_encoder_action_input_proj.weight,
    )
    for step in range(3):
        before = ema.detach().clone()
        policy.train()
        policy.forward(make_batch(step))[0].backward()
        optimizer.step()
        optimizer.zero_grad()
        policy.update()
        decay = min(0.5, (1 + step) / (10 + step))  # 0.1, 0.18, 0.25: warmed up
        torch.testing.assert_close(ema, decay * before + (1 - decay) * raw.detach())
    assert policy.ema_updates.item() == 3 and not torch.equal(ema, raw)

    obs = observation(make_batch())
    policy.eval()
    with torch.no_grad():
        expected = policy.ema_model(policy._images_listed(obs))[0]
    torch.testing.assert_close(policy.predict_action_chunk(obs), expected, rtol=0, atol=0)
    policy.save_pretrained(tmp_path)
    loaded = ACTModifiedPolicy.from_pretrained(tmp_path)
    assert loaded.ema_updates.item() == 3
    torch.testing.assert_close(loaded.predict_action_chunk(obs), expected, rtol=0, atol=0)


def test_warm_start_from_a_stock_act_checkpoint(tmp_path, monkeypatch):
    torch.manual_seed(1)
    act = ACTPolicy(
        ACTConfig(
            input_features=dataset_features(labels=False), output_features=dict(ACTION_FEATURES), **SMALL
        )
    )
    act.save_pretrained(tmp_path / "act")
    warm = make_policy(variant="full", use_phase_predictor=True, init_from_act=str(tmp_path / "act"))
    ours = warm.state_dict()
    for name, value in act.state_dict().items():
        assert torch.equal(ours[name], value), name
    assert any(name.startswith("model.phase_head") for name in ours)
    # A relative folder is stored resolved: config.json must name the same folder from any working directory.
    monkeypatch.chdir(tmp_path)
    assert make_policy(variant="full", init_from_act="act").config.init_from_act == str(
        (tmp_path / "act").resolve()
    )
    # Reloading the act_modified checkpoint uses its own weights, not the warm start again.
    (tmp_path / "act" / "model.safetensors").unlink()
    warm.save_pretrained(tmp_path / "ours")
    ACTModifiedPolicy.from_pretrained(tmp_path / "ours")


def test_warm_start_from_an_incompatible_checkpoint_is_refused(tmp_path):
    other = ACTPolicy(
        ACTConfig(
            input_features=dataset_features(labels=False),
            output_features=dict(ACTION_FEATURES),
            **SMALL | {"dim_model": 16, "dim_feedforward": 32},
        )
    )
    other.save_pretrained(tmp_path)
    with pytest.raises(ValueError, match="init_from_act=.*does not fit"):
        make_policy(variant="standard", init_from_act=str(tmp_path))


def test_prompts_are_encoded_once_per_episode_and_again_after_training():
    policy = make_policy(variant="full")
    policy.eval()
    batch = observation(make_batch())
    first = policy.predict_action_chunk(batch)
    cache = policy.model._prompt_cache
    assert cache is not None
    assert torch.equal(policy.predict_action_chunk(batch), first) and policy.model._prompt_cache is cache
    policy.train()
    assert policy.model._prompt_cache is None
    with torch.no_grad():
        policy.model.encoder_img_feat_input_proj.weight.mul_(2.0)
    policy.eval()
    assert not torch.allclose(policy.predict_action_chunk(batch), first)
