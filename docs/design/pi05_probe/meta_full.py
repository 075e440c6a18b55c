# ruff: noqa: E402, E741, N806, SIM115  (a probe script kept for reference, not package code)
"""Full-size pi05 on the meta device (no real memory): param count + state-dict keys vs a no-param subclass."""

import os
import resource
import time

os.environ.setdefault("HF_HUB_OFFLINE", "1")
from dataclasses import dataclass

import torch

torch.set_num_threads(1)
from lerobot.configs import FeatureType, PolicyFeature, PreTrainedConfig
from lerobot.policies.pi05.configuration_pi05 import PI05Config
from lerobot.policies.pi05.modeling_pi05 import PI05Policy


@PreTrainedConfig.register_subclass("pi05_grounded_probe")
@dataclass
class PI05GroundedConfig(PI05Config):
    attn_reg_weight: float = 0.1


class PI05GroundedPolicy(PI05Policy):
    config_class = PI05GroundedConfig
    name = "pi05_grounded_probe"


def cfg(cls):
    c = cls(device="cpu")  # device must be a real device string for PreTrainedConfig.__post_init__
    c.input_features = {
        f"observation.images.cam{i}": PolicyFeature(type=FeatureType.VISUAL, shape=(3, 224, 224))
        for i in range(2)
    }
    c.input_features["observation.state"] = PolicyFeature(type=FeatureType.STATE, shape=(14,))
    c.output_features = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(14,))}
    return c


def build(cls, ccls):
    c = cfg(ccls)
    c.device = "meta"  # after __post_init__ validation; makes PI05Policy.__init__'s self.model.to(config.device) a no-op
    t0 = time.perf_counter()
    with torch.device("meta"):
        try:
            p = cls(c)
        except Exception as e:
            print(f"  {cls.__name__}(cfg) under meta raised {type(e).__name__}: {str(e)[:200]}")
            raise
    print(
        f"  built {cls.__name__} in {time.perf_counter() - t0:.1f}s rss={resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f}MB"
    )
    return p


p = build(PI05Policy, PI05Config)
print("device of a param:", next(p.parameters()).device, "dtype:", next(p.parameters()).dtype)
n = sum(x.numel() for x in p.parameters())
sd = p.state_dict()
n_sd = sum(v.numel() for v in sd.values())
pg = p.model.paligemma_with_expert
parts = {
    "vision_tower": sum(x.numel() for x in pg.paligemma.model.vision_tower.parameters()),
    "projector": sum(x.numel() for x in pg.paligemma.model.multi_modal_projector.parameters()),
    "paligemma LM (incl embed)": sum(x.numel() for x in pg.paligemma.model.language_model.parameters()),
    "paligemma lm_head (tied?)": pg.paligemma.lm_head.weight.numel(),
    "gemma_expert (incl lm_head)": sum(x.numel() for x in pg.gemma_expert.parameters()),
    "gemma_expert lm_head": pg.gemma_expert.lm_head.weight.numel(),
}
print(f"params (dedup) = {n:,}; state_dict keys = {len(sd)}; state_dict numel (with tied dups) = {n_sd:,}")
print(
    "tied lm_head is embed:",
    pg.paligemma.lm_head.weight is pg.paligemma.model.language_model.embed_tokens.weight,
)
for k, v in parts.items():
    print(f"  {k}: {v:,}")
print(
    "vision tokens/cam:",
    pg.paligemma.config.text_config.num_image_tokens,
    "patch",
    pg.paligemma.config.vision_config.patch_size,
)
del p
q = build(PI05GroundedPolicy, PI05GroundedConfig)
sd2 = q.state_dict()
print(
    "subclass keys identical:",
    list(sd.keys()) == list(sd2.keys()),
    "shapes identical:",
    all(sd[k].shape == sd2[k].shape for k in sd),
)
print("some keys:", [k for k in sd if "layers.0.self_attn" in k][:8])
print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f}MB")
