"""`pi05_grounded`: LeRobot's π0.5 with the paper's eq. (1) on the action expert's attention over the image
patches, and weight loading that fails loudly.

The attention weights are computed by LeRobot's Gemma layers and thrown away; they are taken by swapping
`modeling_gemma.eager_attention_forward` (which π0.5's joint layers look up at call time) for the duration of
a training forward. The joint sequence is [camera patches | language | action queries]: the action queries'
rows over the patch columns are kept, as small copies, never as views of the full L x L map. Under gradient
checkpointing the layers run again during backward; those recomputations are not stored again.
"""

import contextlib
import logging
from pathlib import Path

import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.common.vla_utils import resize_with_pad_torch
from lerobot.policies.pi05.modeling_pi05 import PI05Policy
from torch import Tensor
from transformers.models.gemma import modeling_gemma

from lerobot_condground.core.grounding import overlaps
from lerobot_condground.core.labels import OBS_PHASE
from lerobot_condground.core.routing import step_masks

from .configuration_pi05_grounded import PI05GroundedConfig

logger = logging.getLogger(__name__)
WEIGHTS = "model.safetensors"


class ExpertAttention:
    """Keeps, per selected layer of one forward pass, the attention of the last `queries` rows (the action
    chunk) over the first `keys` columns (the image patches): (B, 8 heads, queries, keys)."""

    def __init__(self, layers: set[int], queries: int, keys: int):
        self.layers, self.queries, self.keys = layers, queries, keys
        self.maps: list[Tensor] = []
        self._calls = 0
        self._eager = modeling_gemma.eager_attention_forward

    def __call__(self, module, query, key, value, attention_mask, scaling, dropout=0.0, **kwargs):
        out, weights = self._eager(
            module, query, key, value, attention_mask, scaling, dropout=dropout, **kwargs
        )
        # -1 outside autograd's backward: a checkpointed layer recomputed during backward is skipped.
        if torch._C._current_graph_task_id() == -1:
            if self._calls in self.layers:
                # Plain slicing and a copy only: an op that saves tensors for backward (indexing the heads)
                # would differ between the forward and the checkpoint's recomputation.
                self.maps.append(weights[:, :, -self.queries :, : self.keys].clone())
            self._calls += 1
        return out, weights

    @contextlib.contextmanager
    def capturing(self):
        modeling_gemma.eager_attention_forward = self
        try:
            yield self
        finally:
            modeling_gemma.eager_attention_forward = self._eager


class PI05GroundedPolicy(PI05Policy):
    config_class = PI05GroundedConfig
    name = "pi05_grounded"

    def __init__(self, config: PI05GroundedConfig, **kwargs):
        super().__init__(config, **kwargs)
        depth = len(self.model.paligemma_with_expert.gemma_expert.model.layers)
        bad = [layer for layer in config.grounding_layers if not -depth <= layer < depth]
        if bad:
            raise ValueError(
                f"grounding_layers={bad} are not layers of the action expert; allowed: {-depth}..{depth - 1}"
            )
        self.grounding_layers = {layer % depth for layer in config.grounding_layers}
        vision = self.model.paligemma_with_expert.paligemma.config.vision_config
        self.patch_grid = config.image_resolution[0] // vision.patch_size

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path, *, config=None, strict: bool = True, **kwargs):
        """Like pi05's, except that weights that cannot be found, or do not fit, are an error: pi05's own
        loader prints a warning and returns random weights."""
        from safetensors.torch import load_file

        weights = weights_file(pretrained_name_or_path, kwargs)
        if config is None:
            config = PreTrainedConfig.from_pretrained(pretrained_name_or_path, **_hub_kwargs(kwargs))
        policy = cls(config)
        state = policy.prepared_state(load_file(str(weights)))
        problem = policy.weights_mismatch(state)
        if problem:
            if strict:
                raise ValueError(f"{weights} does not fit pi05_grounded with this configuration: {problem}")
            logger.warning("%s: %s", weights, problem)
        policy.load_state_dict(state, strict=False)
        policy.to(config.device)
        policy.eval()
        return policy

    def prepared_state(self, state: dict[str, Tensor]) -> dict[str, Tensor]:
        """A pi05 checkpoint's tensors under this policy's names (pi05's own key fixes, then `model.`)."""
        state = self._fix_pytorch_state_dict_keys(state, self.config)
        return {key if key.startswith("model.") else f"model.{key}": value for key, value in state.items()}

    def weights_mismatch(self, state: dict[str, Tensor]) -> str | None:
        """What keeps `state` from loading strictly (names and shapes; meta tensors do), or None."""
        own = self.state_dict()
        # safetensors stores a tied tensor once: a missing name is fine when its tensor is loaded by another.
        names_of: dict[int, list[str]] = {}
        for name, tensor in [*self.named_parameters(remove_duplicate=False), *self.named_buffers()]:
            names_of.setdefault(id(tensor), []).append(name)
        loaded = {id_ for id_, names in names_of.items() if any(n in state for n in names)}
        tied_to_loaded = {n for id_ in loaded for n in names_of[id_]}
        missing = [k for k in own if k not in state and k not in tied_to_loaded]
        unexpected = [k for k in state if k not in own]
        shapes = [
            f"{k} {tuple(state[k].shape)} vs {tuple(own[k].shape)}"
            for k in state
            if k in own and tuple(state[k].shape) != tuple(own[k].shape)
        ]
        if not (missing or unexpected or shapes):
            return None
        return (
            f"{len(missing)} missing weights {missing[:3]}, {len(unexpected)} unexpected {unexpected[:3]}, "
            f"{len(shapes)} of another shape {shapes[:3]} (paligemma_variant, action_expert_variant, "
            "max_state_dim and max_action_dim must be the checkpoint's)"
        )

    def forward(self, batch: dict[str, Tensor], reduction: str = "mean") -> tuple[Tensor, dict]:
        cfg = self.config
        if not (cfg.use_grounding_loss and self.training):
            return super().forward(batch, reduction)
        cameras = [c for c in cfg.image_features if c in batch]
        supervised = {c: cfg.grounding_cameras[c] for c in cameras if c in cfg.grounding_cameras}
        missing = [key for key in (OBS_PHASE, *supervised.values()) if key not in batch]
        if missing or not supervised:
            raise ValueError(
                f"pi05_grounded's grounding loss needs {missing or list(cfg.grounding_cameras.values())} in the "
                "training batch: train on a dataset recorded with labels (`condground record`), with the "
                "policy's own preprocessor (it decodes them)"
            )
        n_keys = len(cameras) * self.patch_grid**2
        capture = ExpertAttention(self.grounding_layers, cfg.chunk_size, n_keys)
        with capture.capturing():
            flow, info = super().forward(batch, reduction="none")
        on_relevant, on_distractors, has_referent = self._overlaps(capture.maps, batch, cameras, supervised)
        pull = (1 - on_relevant) * has_referent
        per_sample = flow + cfg.grounding_pos_weight * pull + cfg.grounding_neg_weight * on_distractors
        n_supervised = has_referent.sum().clamp_min(1)
        info |= {
            "flow_loss": flow.mean().item(),
            "grounding_on_relevant": ((on_relevant * has_referent).sum() / n_supervised).item(),
            "grounding_on_distractors": on_distractors.mean().item(),
            "grounding_supervised_fraction": has_referent.mean().item(),
        }
        loss = per_sample if reduction == "none" else per_sample.mean()
        info["loss"] = per_sample.mean().item()
        return loss, info

    def _overlaps(self, maps: list[Tensor], batch: dict, cameras: list[str], supervised: dict[str, str]):
        """Per sample, averaged over the supervised cameras: <A, M_phi>, <A, M_d> (float32) and whether any
        camera sees a referent (1.0 / 0.0)."""
        # (B, keys): layers, chosen heads and action queries averaged, in float32 whatever the model's dtype.
        heads = self.config.grounding_heads or slice(None)
        attention = torch.stack([m[:, heads].float().mean(dim=(1, 2)) for m in maps]).mean(0)
        per_camera = self.patch_grid**2
        phase = batch[OBS_PHASE]
        relevant_sum, distractor_sum, referents = 0, 0, 0
        for camera, seg_key in supervised.items():
            j = cameras.index(camera)
            a = attention[:, j * per_camera : (j + 1) * per_camera]
            a = (a / a.sum(-1, keepdim=True).clamp_min(1e-12)).view(-1, self.patch_grid, self.patch_grid)
            relevant, distractors = step_masks(torch.as_tensor(batch[seg_key]).to(a.device), phase)
            # The masks go through the frames' own resize-with-padding, so they cover the same patches.
            relevant, distractors = (self._as_model_input(m) for m in (relevant, distractors))
            on_relevant, on_distractors = overlaps(a, relevant, distractors)
            seen = (relevant.flatten(1).amax(1) > 0).float()
            relevant_sum = relevant_sum + on_relevant * seen
            distractor_sum = distractor_sum + on_distractors
            referents = referents + seen
        n = len(supervised)
        return relevant_sum / referents.clamp_min(1), distractor_sum / n, (referents > 0).float()

    def _as_model_input(self, mask: Tensor) -> Tensor:
        side = self.config.image_resolution
        return resize_with_pad_torch(mask.float().unsqueeze(1), *side).squeeze(1)


def _hub_kwargs(kwargs: dict) -> dict:
    keys = ("force_download", "cache_dir", "token", "revision", "local_files_only", "proxies")
    return {k: kwargs[k] for k in keys if k in kwargs}


def weights_file(source, kwargs: dict | None = None) -> Path:
    """The checkpoint's weights: `model.safetensors` of a local directory (a link must resolve), or of a hub
    repository (the local cache when offline)."""
    path = Path(source)
    if path.is_dir():
        weights = path / WEIGHTS
        if not weights.resolve().is_file():
            raise FileNotFoundError(
                f"{weights} is missing (or a broken link): a pi05_grounded checkpoint directory needs its weights"
            )
        return weights
    from huggingface_hub import hf_hub_download

    try:
        return Path(hf_hub_download(str(source), WEIGHTS, **_hub_kwargs(kwargs or {})))
    except Exception as e:
        raise FileNotFoundError(
            f"Cannot get {WEIGHTS} of {source!r} ({type(e).__name__}): give a local checkpoint directory, or "
            "download it first (`hf download <repo>` with network access)"
        ) from e
