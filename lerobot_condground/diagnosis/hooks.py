"""Forward hooks, loading and the cross-attention head reader for ACT-family checkpoints (stock `act`,
`act_modified`), shared by the representation diagnostics, the attention views and the fit."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lerobot_condground.core.conditions import check_condition, check_task
from lerobot_condground.core.configs import EvalEnvConfig, PolicyRefConfig
from lerobot_condground.evaluation.checkpoints import (
    CAMERA_PREFIX,
    check_env_fits,
    describe_checkpoint,
    load_policy,
    resolve_device,
)
from lerobot_condground.evaluation.rollout import EnvSpec


def check_act_family(loaded) -> None:
    """ACT or any policy whose config subclasses LeRobot's ACTConfig (act_modified)."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.act.configuration_act import ACTConfig

    try:
        config_class = PreTrainedConfig.get_choice_class(loaded.policy_type)
    except Exception:  # noqa: BLE001 - unknown type names raise various errors in draccus
        config_class = None
    if config_class is None or not issubclass(config_class, ACTConfig):
        act_types = sorted(
            name
            for name, cls in PreTrainedConfig.get_known_choices().items()
            if isinstance(cls, type) and issubclass(cls, ACTConfig)
        )
        raise ValueError(
            f"Checkpoint {loaded.path!r} is a {loaded.policy_type!r} policy; this diagnosis needs an ACT-family "
            f"checkpoint (policy types: {', '.join(act_types)})"
        )


def env_spec_for(env: EvalEnvConfig, loaded, condition: str | None = None) -> EnvSpec:
    """The EnvSpec that renders what the checkpoint reads, prompt crops included; the camera size defaults
    to the checkpoint's, the condition to --env.condition, else clean."""
    try:
        check_task(env.task)
    except ValueError as err:
        raise ValueError(f"--env.task={env.task!r}: {err}") from None
    condition = check_condition(condition or env.condition or "clean", "--env.condition")
    if env.episode_length < 1:
        raise ValueError(f"--env.episode_length={env.episode_length} must be a positive number of steps")
    spec = EnvSpec.for_checkpoint(env, loaded, condition, prompts=True)
    check_env_fits(loaded, spec.lerobot_config())
    return spec


def load_act_family(policy: PolicyRefConfig, env: EvalEnvConfig, condition: str | None = None):
    """(LoadedPolicy, EnvSpec) after checking the checkpoint is ACT-family and fits the env."""
    if not policy.checkpoints():
        raise ValueError("--policy.path is required: an ACT-family checkpoint directory or hub id")
    path = policy.single()
    described = describe_checkpoint(path, policy.label, trust_remote_code=policy.trust_remote_code)
    check_act_family(described)
    spec = env_spec_for(env, described, condition)
    loaded = load_policy(described, spec.lerobot_config(), resolve_device(policy.device))
    return loaded, spec


def model_inputs(policy, batch: dict) -> dict:
    """The pre-processed batch as ACT's model takes it (cameras listed under observation.images), as
    ACTPolicy.predict_action_chunk builds it; the batch itself is left as it is."""
    from lerobot.utils.constants import OBS_IMAGES

    inputs = dict(batch)
    if policy.config.image_features:
        inputs[OBS_IMAGES] = [batch[key] for key in policy.config.image_features]
    return inputs


def acting_model(policy):
    """The model whose weights act: act_modified's moving average when it keeps one, else `policy.model`."""
    return getattr(policy, "acting_model", policy.model)


class ACTProbe:
    """Forward hooks on an ACT-family model (`acting_model(policy)`) for one forward pass at a time.

    Captures per camera the backbone feature map (only for the camera images of the batch, not for
    prompt crops that act_modified passes through the same backbone), the encoder output, the
    decoder output and, with `attention_layer` set, the query and key of that decoder layer's
    cross-attention. Use as a context manager; `forward(policy, batch)` runs one pass."""

    def __init__(self, model, attention_layer: int | None = None):
        self.model = model
        self.attention_layer = attention_layer
        self._handles = []
        self._cameras: list = []
        self._camera_call = False
        self.forward_passes = 0
        self.clear()

    def clear(self) -> None:
        self.feature_maps = []
        self.encoder_out = None
        self.decoder_out = None
        self.query_key = None

    def __enter__(self):
        model = self.model

        # A camera frame is known by identity before any other pre-hook runs: `channels_last` swaps the frame
        # for a copy in channels-last order, and prompt crops pass through the same backbone.
        def before_backbone(module, args):
            self._camera_call = any(args[0] is image for image in self._cameras)

        def on_backbone(module, args, output):
            if self._camera_call:
                self.feature_maps.append(output["feature_map"])

        def on_encoder(module, args, output):
            self.encoder_out = output

        def on_decoder(module, args, output):
            self.decoder_out = output

        self._handles = [
            model.backbone.register_forward_pre_hook(before_backbone, prepend=True),
            model.backbone.register_forward_hook(on_backbone),
            model.encoder.register_forward_hook(on_encoder),
            model.decoder.register_forward_hook(on_decoder),
        ]
        if self.attention_layer is not None:

            def on_attention(module, args, kwargs):
                names = ("query", "key")
                values = [args[i] if len(args) > i else kwargs[name] for i, name in enumerate(names)]
                self.query_key = tuple(values)

            mha = model.decoder.layers[self.attention_layer].multihead_attn
            self._handles.append(mha.register_forward_pre_hook(on_attention, with_kwargs=True))
        return self

    def __exit__(self, *exc):
        for handle in self._handles:
            handle.remove()
        self._handles = []

    def forward(self, policy, batch: dict):
        """One model forward (call under torch.inference_mode); returns the model's outputs."""
        from lerobot.utils.constants import OBS_IMAGES

        self.clear()
        inputs = model_inputs(policy, batch)
        self._cameras = list(inputs.get(OBS_IMAGES, []))
        try:
            out = acting_model(policy)(inputs)
        finally:
            self._cameras = []
        self.forward_passes += 1
        return out

    def activations(self) -> dict:
        """layer -> (B, D) float32 numpy."""
        return {
            "vision_encoder": torch_cat([fm.float().mean(dim=(2, 3)) for fm in self.feature_maps]),
            "memory": self.encoder_out.float().mean(0).cpu().numpy(),
            "decoder": self.decoder_out.float().mean(0).cpu().numpy(),
        }


def torch_cat(tensors) -> np.ndarray:
    import torch

    return torch.cat(tensors, dim=1).cpu().numpy()


@dataclass
class AttentionTarget:
    """Which head, layer and camera grid to read, resolved against a policy config."""

    head: int
    layer: int
    camera: str  # short name: top, wrist
    camera_index: int
    n_1d_tokens: int


def resolve_target(
    config, head: int | None = None, layer: int = -1, camera: str | None = None
) -> AttentionTarget:
    """Defaults: act_modified's supervised `attention_head` (0 for stock ACT), the last decoder layer, its
    `attention_camera` (else the first camera); the messages name `condground attention`'s flags."""
    n_heads, n_layers = config.n_heads, config.n_decoder_layers
    head = head if head is not None else int(getattr(config, "attention_head", 0) or 0)
    if isinstance(head, bool) or not 0 <= head < n_heads:
        raise ValueError(
            f"--attention.head={head} is out of range; allowed: 0..{n_heads - 1} (the policy has n_heads={n_heads})"
        )
    if isinstance(layer, bool) or not -n_layers <= layer < n_layers:
        raise ValueError(
            f"--attention.layer={layer} is out of range; allowed: {-n_layers}..{n_layers - 1} "
            f"(the policy has n_decoder_layers={n_layers})"
        )
    cameras = [key[len(CAMERA_PREFIX) :] for key in config.image_features]
    if camera is None:
        default = getattr(config, "attention_camera", None)
        camera = (
            default[len(CAMERA_PREFIX) :] if default and default.startswith(CAMERA_PREFIX) else cameras[0]
        )
    if camera not in cameras:
        raise ValueError(
            f"--attention.camera={camera!r} is not a camera of the policy; allowed: {', '.join(cameras)}"
        )
    n_1d = 1 + (config.robot_state_feature is not None) + (config.env_state_feature is not None)
    return AttentionTarget(
        head=head,
        layer=layer % n_layers,
        camera=camera,
        camera_index=cameras.index(camera),
        n_1d_tokens=n_1d,
    )


def camera_attention(probe: ACTProbe, target: AttentionTarget) -> tuple[np.ndarray, np.ndarray]:
    """After a probe forward at target.layer: ((B, h, w) attention over the camera's grid summing to 1,
    (B,) share of the head's attention that fell on that camera's tokens before renormalizing)."""
    from lerobot_condground.policies.act_modified.modeling_act_modified import (
        grid_attention,
        head_log_attention,
    )

    query, key = probe.query_key
    mha = probe.model.decoder.layers[target.layer].multihead_attn
    log_weights = head_log_attention(mha, query, key, target.head)  # (B, queries, tokens)
    grids = [tuple(fm.shape[-2:]) for fm in probe.feature_maps]
    h, w = grids[target.camera_index]
    start = target.n_1d_tokens + sum(a * b for a, b in grids[: target.camera_index])
    if start + h * w > log_weights.shape[-1]:
        raise RuntimeError(
            f"token layout mismatch: camera grid {h}x{w} at {start} beyond {log_weights.shape[-1]} tokens"
        )
    on_camera = log_weights[:, :, start : start + h * w]
    share = on_camera.exp().sum(-1).mean(1)
    return grid_attention(on_camera).view(-1, h, w).cpu().numpy(), share.cpu().numpy()
