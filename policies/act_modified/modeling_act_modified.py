"""`act_modified`: LeRobot's ACT with visual prompts, a phase predictor and a supervised
cross-attention head (paper eq. 1, Figure 1).

Everything ACT has keeps ACT's module names, so a stock ACT checkpoint loads into it
(`--policy.init_from_act=...`) and, with every component off, it computes exactly what ACT computes.

Design choices:
- Prompts go through the camera backbone (shared, not a separate CNN): the crop is then described
  in the same feature space as the scene tokens it must be matched against, and it inherits the
  backbone's pretraining. It is pooled to one token with its own learned embedding and no 2-D
  position, so it says what the target looks like, never where it is.
- The phase predictor reads pooled backbone features and the robot state, before the transformer,
  so choosing the prompt never depends on the prompt itself.
- In training the prompt is chosen by the phase label (teacher forcing, `phase_teacher_forcing=1`):
  a still-untrained predictor would otherwise feed the wrong crop half the time early on and teach
  the policy to ignore prompts. Lower it for scheduled sampling.
- The supervised attention is recomputed from the head's own query/key projections, so it is the
  softmax before dropout, and the stock fused attention kernel still serves the forward pass.
"""

import contextlib
import copy
import dataclasses
import logging
import math
from pathlib import Path

import einops
import torch
import torch.nn.functional as F  # noqa: N812
import torchvision
from lerobot.policies.act.modeling_act import ACT, ACTPolicy, ACTTemporalEnsembler
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE
from torch import Tensor, nn
from torchvision.models._utils import IntermediateLayerGetter

from lerobot_condground.core.grounding import overlaps
from lerobot_condground.core.labels import (
    OBS_PHASE,
    OBS_PROMPT_OBJECT,
    OBS_PROMPT_RECEPTACLE,
    OBS_SEGMENTATION,
    phase_masks,
)

from .configuration_act_modified import NARROW_RESNET_LAYERS, ACTModifiedConfig

logger = logging.getLogger(__name__)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class RecordingMultiheadAttention(nn.MultiheadAttention):
    """nn.MultiheadAttention that keeps its last query and key while `capture` is set, so one head's
    attention can be recomputed before dropout. Same parameters and names as its parent."""

    capture = False
    captured: tuple[Tensor, Tensor] | None = None

    def forward(self, query, key, value, **kwargs):
        if self.capture:
            self.captured = (query, key)
        return super().forward(query, key, value, **kwargs)

    def head_log_attention(self, head: int) -> Tensor:
        """(B, queries, keys) log-softmax attention of `head` for the captured inputs, before dropout."""
        query, key = self.captured
        self.captured = None
        return head_log_attention(self, query, key, head)


def head_log_attention(mha: nn.MultiheadAttention, query: Tensor, key: Tensor, head: int) -> Tensor:
    """(B, queries, keys) log-softmax attention of one head of any nn.MultiheadAttention (packed in_proj,
    sequence-first inputs as ACT uses them: query (T, B, E), key (S, B, E)), before dropout, in float32."""
    embed_dim = mha.embed_dim
    dim = embed_dim // mha.num_heads
    rows = slice(head * dim, (head + 1) * dim)
    w_q, w_k = mha.in_proj_weight[:embed_dim][rows], mha.in_proj_weight[embed_dim : 2 * embed_dim][rows]
    b_q, b_k = mha.in_proj_bias[:embed_dim][rows], mha.in_proj_bias[embed_dim : 2 * embed_dim][rows]
    q = F.linear(query, w_q, b_q)  # (T, B, d)
    k = F.linear(key, w_k, b_k)  # (S, B, d)
    with torch.autocast(device_type=q.device.type, enabled=False):  # autocast would run einsum in bf16
        return torch.einsum("tbd,sbd->bts", q.float(), k.float()).div(math.sqrt(dim)).log_softmax(-1)


def grid_attention(log_attention: Tensor) -> Tensor:
    """(B, tokens) attention over one camera's tokens, averaged over the queries and renormalized to sum to 1
    (the paper's A), from their (B, queries, tokens) log-attention. Shifted by its maximum before `exp`: a
    head that gives nearly all its mass to the 1D tokens leaves the camera 1e-24 of it (measured on `full`),
    which rounds to 0, and 0/0 turned a whole training run to NaN. The shift cancels in the ratio."""
    weights = (log_attention - log_attention.amax(dim=(1, 2), keepdim=True)).exp().mean(1)
    return weights / weights.sum(-1, keepdim=True)


def _norm_layer(name: str):
    if name == "batchnorm":
        return nn.BatchNorm2d
    return lambda channels, **_: nn.GroupNorm(32, channels)


def _resnet(config: ACTModifiedConfig) -> nn.Module:
    norm_layer = _norm_layer(config.backbone_norm)
    if config.backbone_width == 64:
        return getattr(torchvision.models, config.vision_backbone)(
            replace_stride_with_dilation=[False, False, config.replace_final_stride_with_dilation],
            weights=config.pretrained_backbone_weights,
            norm_layer=norm_layer,
        )
    from timm.models.resnet import BasicBlock, ResNet

    width = config.backbone_width
    return ResNet(
        BasicBlock,
        NARROW_RESNET_LAYERS[config.vision_backbone],
        channels=(width, 2 * width, 4 * width, 8 * width),
        stem_width=width,
        norm_layer=norm_layer,
        output_stride=16 if config.replace_final_stride_with_dilation else 32,
    )


class ACTModified(ACT):
    def __init__(self, config: ACTModifiedConfig):
        rebuild = config.image_features and (
            config.backbone_norm != "frozen_batchnorm"
            or config.backbone_width != 64
            or config.backbone_layer != "layer4"
        )
        # ACT's own backbone is replaced below when rebuilt; built without dilation, which torchvision's
        # BasicBlock refuses and the narrow ResNet takes.
        super().__init__(
            dataclasses.replace(config, replace_final_stride_with_dilation=False) if rebuild else config
        )
        self.config = config
        dim = config.dim_model
        if rebuild:
            # ACT builds its ResNet with FrozenBatchNorm2d whatever the weights; rebuilt the same way with
            # normalization that trains, and narrower if asked.
            resnet = _resnet(config)
            # The getter keeps the stages up to the one it returns: a layer3 cut never builds layer4's weights.
            self.backbone = IntermediateLayerGetter(
                resnet, return_layers={config.backbone_layer: "feature_map"}
            )
            last = getattr(resnet, config.backbone_layer)[-1]
            channels = (last.conv3 if hasattr(last, "conv3") else last.conv2).out_channels
            if channels != self.encoder_img_feat_input_proj.in_channels:
                self.encoder_img_feat_input_proj = nn.Conv2d(channels, dim, kernel_size=1)
        if config.use_phase_predictor:
            pooled = self.encoder_img_feat_input_proj.in_channels * len(config.image_features)
            state = config.robot_state_feature.shape[0] if config.robot_state_feature else 0
            self.phase_head = nn.Sequential(
                nn.Linear(pooled + state, config.phase_head_dim),
                nn.ReLU(),
                nn.Linear(config.phase_head_dim, 2),
            )
        self._prompt_cache: tuple[Tensor, Tensor] | None = None
        self.register_load_state_dict_pre_hook(lambda module, *_: setattr(module, "_prompt_cache", None))
        if config.use_prompts:
            self.prompt_pos_embed = nn.Embedding(2 if config.prompt_selection == "both" else 1, dim)
            self.prompt_kind_embed = nn.Embedding(2, dim)  # object or receptacle crop
            self.register_buffer(
                "prompt_mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False
            )
            self.register_buffer("prompt_std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        if config.use_attention_loss:
            stock = self.decoder.layers[-1].multihead_attn
            recording = RecordingMultiheadAttention(dim, config.n_heads, dropout=config.dropout)
            recording.load_state_dict(stock.state_dict())
            self.decoder.layers[-1].multihead_attn = recording

    def forward(self, batch: dict[str, Tensor], with_attention: bool = False):
        """ACT's forward with the prompt token(s) appended to the memory. Returns (actions, (mu, log_sigma_x2),
        aux) with aux["phase_logits"] (B, 2), aux["phase"] (B,) the phase whose prompt was fed (none with
        prompt_selection=both), and with
        `with_attention` aux["attention"] (B, h, w): the supervised head's attention over the camera's
        token grid, averaged over action queries, normalized to sum 1 on the grid (`attention_normalization`
        camera) or left as the head's share of the whole memory (memory)."""
        cfg = self.config
        images = batch[OBS_IMAGES]
        batch_size = images[0].shape[0]
        mu, log_sigma_x2, latent = self._latent(batch, batch_size)

        tokens = [self.encoder_latent_input_proj(latent)]
        pos_embed = list(self.encoder_1d_feature_pos_embed.weight.unsqueeze(1))
        if cfg.robot_state_feature:
            tokens.append(self.encoder_robot_state_input_proj(batch[OBS_STATE]))
        if cfg.env_state_feature:
            tokens.append(self.encoder_env_state_input_proj(batch[OBS_ENV_STATE]))
        n_1d_tokens = len(tokens)
        feature_maps = []
        for img in images:
            feature_map = self.backbone(img)["feature_map"]
            feature_maps.append(feature_map)
            cam_pos_embed = self.encoder_cam_feat_pos_embed(feature_map).to(dtype=feature_map.dtype)
            cam_features = self.encoder_img_feat_input_proj(feature_map)
            tokens.extend(list(einops.rearrange(cam_features, "b c h w -> (h w) b c")))
            pos_embed.extend(list(einops.rearrange(cam_pos_embed, "b c h w -> (h w) b c")))

        aux: dict[str, Tensor] = {}
        if cfg.use_phase_predictor:
            pooled = [fm.mean(dim=(2, 3)) for fm in feature_maps]
            if cfg.phase_head_detach:
                pooled = [p.detach() for p in pooled]
            if cfg.robot_state_feature:
                pooled.append(batch[OBS_STATE])
            aux["phase_logits"] = self.phase_head(torch.cat(pooled, dim=1))
        if cfg.use_prompts and cfg.prompt_selection == "both":
            tokens.extend(self._prompt_tokens(batch))
            pos_embed.extend(list(self.prompt_pos_embed.weight.unsqueeze(1)))
        elif cfg.use_prompts:
            phase = self._prompt_phase(batch, aux["phase_logits"])
            aux["phase"] = phase
            tokens.append(self._prompt_token(batch, phase))
            pos_embed.append(self.prompt_pos_embed.weight)

        tokens = torch.stack(tokens, axis=0)
        pos_embed = torch.stack(pos_embed, axis=0)
        encoder_out = self.encoder(tokens, pos_embed=pos_embed)
        cross_attention = self.decoder.layers[-1].multihead_attn
        if with_attention:
            cross_attention.capture = True
        decoder_in = torch.zeros(
            (cfg.chunk_size, batch_size, cfg.dim_model), dtype=pos_embed.dtype, device=pos_embed.device
        )
        try:
            decoder_out = self.decoder(
                decoder_in,
                encoder_out,
                encoder_pos_embed=pos_embed,
                decoder_pos_embed=self.decoder_pos_embed.weight.unsqueeze(1),
            )
        finally:
            if with_attention:
                cross_attention.capture = False
        actions = self.action_head(decoder_out.transpose(0, 1))

        if with_attention:
            h, w = feature_maps[0].shape[-2:]
            camera = list(cfg.image_features).index(cfg.attention_camera)
            start = n_1d_tokens + camera * h * w
            log_attention = cross_attention.head_log_attention(cfg.attention_head)[
                :, :, start : start + h * w
            ]
            if cfg.attention_normalization == "memory":
                aux["attention"] = log_attention.exp().mean(1).view(batch_size, h, w)
            else:
                aux["attention"] = grid_attention(log_attention).view(batch_size, h, w)
        return actions, (mu, log_sigma_x2), aux

    def _latent(self, batch: dict[str, Tensor], batch_size: int):
        """ACT's CVAE: the posterior from the action chunk in training, z = 0 at inference."""
        cfg = self.config
        if not (cfg.use_vae and ACTION in batch and self.training):
            latent = torch.zeros([batch_size, cfg.latent_dim], dtype=torch.float32).to(
                batch[OBS_STATE].device
            )
            return None, None, latent
        cls_embed = einops.repeat(self.vae_encoder_cls_embed.weight, "1 d -> b 1 d", b=batch_size)
        action_embed = self.vae_encoder_action_input_proj(batch[ACTION])
        inputs = [cls_embed, action_embed]
        if cfg.robot_state_feature:
            inputs.insert(1, self.vae_encoder_robot_state_input_proj(batch[OBS_STATE]).unsqueeze(1))
        vae_encoder_input = torch.cat(inputs, axis=1)
        pos_embed = self.vae_encoder_pos_enc.clone().detach()
        cls_joint_is_pad = torch.full((batch_size, len(inputs) - 1), False, device=batch[OBS_STATE].device)
        key_padding_mask = torch.cat([cls_joint_is_pad, batch["action_is_pad"]], axis=1)
        cls_token_out = self.vae_encoder(
            vae_encoder_input.permute(1, 0, 2),
            pos_embed=pos_embed.permute(1, 0, 2),
            key_padding_mask=key_padding_mask,
        )[0]
        latent_pdf_params = self.vae_encoder_latent_output_proj(cls_token_out)
        mu = latent_pdf_params[:, : cfg.latent_dim]
        log_sigma_x2 = latent_pdf_params[:, cfg.latent_dim :]
        return mu, log_sigma_x2, mu + log_sigma_x2.div(2).exp() * torch.randn_like(mu)

    def _prompt_phase(self, batch: dict[str, Tensor], phase_logits: Tensor) -> Tensor:
        predicted = phase_logits.argmax(-1)
        if not (self.training and OBS_PHASE in batch):
            return predicted
        label = batch[OBS_PHASE].reshape(-1).long()
        teacher = torch.rand(label.shape, device=label.device) < self.config.phase_teacher_forcing
        return torch.where(teacher, label, predicted)

    def _prompt_crops(self, batch: dict[str, Tensor]) -> list[Tensor]:
        missing = [key for key in (OBS_PROMPT_OBJECT, OBS_PROMPT_RECEPTACLE) if key not in batch]
        if missing:
            _refuse(
                f"act_modified with prompts needs {missing} in every observation. The condground env sends them "
                "(--env.prompts=true, the default); a robot must provide them as observations."
            )
        return [prompt_as_image(batch[key]) for key in (OBS_PROMPT_OBJECT, OBS_PROMPT_RECEPTACLE)]

    def _prompt_tokens(self, batch: dict[str, Tensor]) -> list[Tensor]:
        """prompt_selection=both: the object's and the receptacle's prompt tokens, each with its kind."""
        crops = self._prompt_crops(batch)
        if self.training:
            features = self._encode_prompts(torch.cat(crops)).view(2, len(crops[0]), -1)
        else:
            features = self._episode_prompt_features(crops)
        return [features[kind] + self.prompt_kind_embed.weight[kind] for kind in (0, 1)]

    def _prompt_token(self, batch: dict[str, Tensor], phase: Tensor) -> Tensor:
        crops = self._prompt_crops(batch)
        if self.training:
            features = self._encode_prompts(torch.where(phase.view(-1, 1, 1, 1) == 0, crops[0], crops[1]))
        else:
            object_features, receptacle_features = self._episode_prompt_features(crops)
            features = torch.where(phase.view(-1, 1) == 0, object_features, receptacle_features)
        return features + self.prompt_kind_embed(phase)

    def _encode_prompts(self, crops: Tensor) -> Tensor:
        crops = (crops - self.prompt_mean) / self.prompt_std
        with _running_batch_norm(self.backbone):
            features = self.backbone(crops)["feature_map"]
        return self.encoder_img_feat_input_proj(features).mean(dim=(2, 3))

    def _episode_prompt_features(self, crops: list[Tensor]) -> Tensor:
        """(object, receptacle) features at inference. The crops stay the same for a whole episode, so
        they are encoded once and reused until they change (or the weights may have: train/load)."""
        both = torch.cat(crops)
        cached = self._prompt_cache
        if cached is None or cached[0].shape != both.shape or not torch.equal(cached[0], both):
            self._prompt_cache = cached = (both, self._encode_prompts(both).view(2, len(crops[0]), -1))
        return cached[1]

    def train(self, mode: bool = True):
        if mode:  # weights may change from here on; eval() is called before every prediction and keeps it
            self._prompt_cache = None
        return super().train(mode)


def _channels_last_input(_module: nn.Module, args: tuple) -> tuple:
    return (args[0].contiguous(memory_format=torch.channels_last), *args[1:])


@contextlib.contextmanager
def _running_batch_norm(backbone: nn.Module):
    """Prompt crops (close-ups of one entity) are another image distribution than the scene. Batch norm in
    training mode would blend their statistics into the running ones the scene is normalized with at
    inference, and normalize the crops by their own batch in training but by those running statistics at
    inference: `full` at 7500 steps lost 22 % of its action accuracy between its two modes (L1 0.058 with
    batch statistics, 0.071 with running ones; `standard`, which encodes no crops, 0.047 and 0.046). Crops
    are encoded with the running statistics in training too, which leaves them to the scene."""
    norms = [m for m in backbone.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm) and m.training]
    for m in norms:
        m.eval()
    try:
        yield
    finally:
        for m in norms:
            m.train()


def _refuse(message: str) -> None:
    """Stock scripts (lerobot-eval, lerobot-record) end on a long traceback: the fix is logged before it
    and is its last line too."""
    logger.error(message)
    raise ValueError(message)


def prompt_as_image(crop: Tensor) -> Tensor:
    """Prompt crops arrive as 0..255 (B, h, w, 3) numbers (dataset or env) or as (B, 3, h, w) images in
    [0, 1] (datasets that store them as image features); returns the latter as float."""
    if crop.shape[-1] == 3:
        return crop.permute(0, 3, 1, 2).float() / 255.0
    return crop.float()


class ACTModifiedPolicy(ACTPolicy):
    config_class = ACTModifiedConfig
    name = "act_modified"
    _loading_checkpoint = False

    def __init__(self, config: ACTModifiedConfig, **kwargs):
        PreTrainedPolicy.__init__(self, config)
        config.validate_features()
        self.config = config
        self.model = ACTModified(config)
        if config.channels_last and config.image_features:
            # The frames, not the weights: parameters in channels-last order would give AdamW's state the same
            # order, which LeRobot's checkpoint writer (safetensors) refuses as non-contiguous.
            self.model.backbone.register_forward_pre_hook(_channels_last_input)
        if config.temporal_ensemble_coeff is not None:
            self.temporal_ensembler = ACTTemporalEnsembler(config.temporal_ensemble_coeff, config.chunk_size)
        self.reset()
        if config.init_from_act and not ACTModifiedPolicy._loading_checkpoint:
            self.warm_start_from(config.init_from_act)
        self.ema_model = None
        if config.ema_decay is not None:
            # A frozen copy: ACT's optimizer groups take only parameters that require grad. Saved in the
            # checkpoint with its update count, so a resumed run continues the same average.
            self.ema_model = copy.deepcopy(self.model).requires_grad_(False)
            self.register_buffer("ema_updates", torch.zeros((), dtype=torch.long))

    @property
    def acting_model(self) -> ACTModified:
        """The weights that act: the moving average when the policy keeps one."""
        return self.model if self.ema_model is None else self.ema_model

    @torch.no_grad()
    def update(self) -> None:
        """Called by lerobot-train after each optimizer step."""
        if self.ema_model is None:
            return
        t = self.ema_updates.item()
        decay = min(self.config.ema_decay, (1 + t) / (10 + t))
        for ema, raw in zip(self.ema_model.parameters(), self.model.parameters(), strict=True):
            ema.lerp_(raw.detach(), 1.0 - decay)
        for ema, raw in zip(self.ema_model.buffers(), self.model.buffers(), strict=True):
            ema.copy_(raw)  # batch-norm statistics follow the raw model's
        self.ema_updates += 1

    @classmethod
    def from_pretrained(cls, *args, **kwargs):
        # The checkpoint's own weights replace the warm start, so do not fetch it again.
        ACTModifiedPolicy._loading_checkpoint = True
        try:
            return super().from_pretrained(*args, **kwargs)
        finally:
            ACTModifiedPolicy._loading_checkpoint = False

    def warm_start_from(self, source: str) -> None:
        """Loads a stock ACT checkpoint (directory with model.safetensors, or hub id) into the shared
        parameters; the prompt and phase modules keep their fresh initialization."""
        from huggingface_hub import hf_hub_download
        from safetensors.torch import load_file

        path = Path(source)
        weights = (
            path / "model.safetensors"
            if path.is_dir()
            else Path(hf_hub_download(source, "model.safetensors"))
        )
        try:
            missing, unexpected = self.load_state_dict(load_file(str(weights)), strict=False)
        except RuntimeError as e:
            raise ValueError(
                f"init_from_act={source!r} does not fit this policy (dim_model, n_heads, cameras, state and "
                f"action sizes must match the checkpoint's): {e}"
            ) from e
        if unexpected:
            raise ValueError(f"init_from_act={source!r} has weights an ACT policy does not: {unexpected[:5]}")
        logger.info("Warm start from %s; fresh: %s", source, ", ".join(missing) or "nothing")

    def _images_listed(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        # The backbone pools and the position embedding follows the feature map, so like stock ACT any frame
        # size runs; eq. (1)'s attention is supervised on the training frames' token grid, so a variant with
        # the attention loss refuses frames of another size wherever it runs.
        for key, feature in self.config.image_features.items() if self.config.use_attention_loss else ():
            if key in batch and tuple(batch[key].shape[-2:]) != tuple(feature.shape[-2:]):
                (h, w), (th, tw) = batch[key].shape[-2:], feature.shape[-2:]
                _refuse(
                    f"{key} frames are {h}x{w}, but this act_modified checkpoint was trained on {th}x{tw} (its "
                    f"attention loss, eq. (1), is defined on that token grid); render at the training size "
                    f"(--env.observation_height={th} --env.observation_width={tw})"
                )
        batch = dict(batch)
        batch[OBS_IMAGES] = [batch[key] for key in self.config.image_features]
        return batch

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor]) -> Tensor:
        self.eval()
        return self.acting_model(self._images_listed(batch))[0]

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        cfg = self.config
        batch = self._images_listed(batch)
        with_attention = cfg.use_attention_loss and OBS_SEGMENTATION in batch
        actions_hat, (mu, log_sigma_x2), aux = self.model(batch, with_attention=with_attention)

        abs_err = F.l1_loss(batch[ACTION], actions_hat, reduction="none")
        valid = ~batch["action_is_pad"].unsqueeze(-1)
        l1_loss = (abs_err * valid).sum() / (valid.sum() * abs_err.shape[-1]).clamp_min(1)
        loss = l1_loss
        loss_dict = {"l1_loss": l1_loss.item()}
        if cfg.use_vae and log_sigma_x2 is not None:
            kld = (-0.5 * (1 + log_sigma_x2 - mu.pow(2) - log_sigma_x2.exp())).sum(-1).mean()
            loss = loss + cfg.kl_weight * kld
            loss_dict["kld_loss"] = kld.item()

        if cfg.use_phase_predictor and OBS_PHASE in batch:
            label = batch[OBS_PHASE].reshape(-1).long()
            phase_loss = F.cross_entropy(aux["phase_logits"], label)
            loss = loss + cfg.phase_loss_weight * phase_loss
            loss_dict["phase_loss"] = phase_loss.item()
            loss_dict["phase_accuracy"] = (aux["phase_logits"].argmax(-1) == label).float().mean().item()
        if with_attention:
            on_relevant, on_distractors = attention_overlaps(
                aux["attention"], batch[OBS_SEGMENTATION], batch[OBS_PHASE].reshape(-1).long()
            )
            loss = loss + cfg.attention_pos_weight * (1 - on_relevant).mean()
            loss = loss + cfg.attention_neg_weight * on_distractors.mean()
            loss_dict["attention_on_relevant"] = on_relevant.mean().item()
            loss_dict["attention_on_distractors"] = on_distractors.mean().item()
        if not torch.isfinite(loss):
            terms = ", ".join(f"{key}={value:.4g}" for key, value in loss_dict.items())
            raise FloatingPointError(
                f"act_modified's loss is not finite ({terms}); stopped before the optimizer step would turn "
                "every weight to NaN, so the last saved checkpoint is intact and can be resumed"
            )
        return loss, loss_dict


def attention_overlaps(attention: Tensor, segmentation: Tensor, phase: Tensor) -> tuple[Tensor, Tensor]:
    """(<A, M_phi>, <A, M_d>) per sample for attention (B, h, w) summing to at most 1 and a label map (B, H, W)."""
    return overlaps(attention, *phase_masks(segmentation, phase))
