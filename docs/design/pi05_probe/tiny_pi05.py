# ruff: noqa: E402, E741, N806, SIM115  (a probe script kept for reference, not package code)
"""Tiny, CPU-only probe of LeRobot 0.6.1 pi05 (no LeRobot files edited, no downloads).

Run:  source .venv/bin/activate && HF_HUB_OFFLINE=1 python docs/design/pi05_probe/tiny_pi05.py
"""

import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

import contextlib  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from unittest import mock  # noqa: E402

import torch  # noqa: E402

torch.set_num_threads(1)

from lerobot.configs import FeatureType, PolicyFeature  # noqa: E402
from lerobot.policies.pi05 import modeling_pi05, processor_pi05  # noqa: E402
from lerobot.policies.pi05.configuration_pi05 import PI05Config  # noqa: E402
from lerobot.policies.pi05.modeling_pi05 import PI05Policy  # noqa: E402
from transformers.models.gemma import modeling_gemma  # noqa: E402

OUT = Path(os.environ.get("PI05_PROBE_DIR", Path(tempfile.gettempdir()) / "pi05_probe"))
TOK_DIR = OUT / "tokenizer"

# ----------------------------------------------------------------------------------------------
# 1. Tiny model: patch three module-level names of modeling_pi05 while the policy is constructed
# ----------------------------------------------------------------------------------------------
TINY_VOCAB = 512
TINY_IMG = 32
TINY_PATCH = 8  # -> (32/8)^2 = 16 image tokens per camera
# NB: compute_layer_complete hard-codes `att_output.reshape(B, -1, 1 * 8 * head_dim)`
# (modeling_pi05.py:116), so num_heads MUST stay 8. head_dim / num_kv_heads / depth must be
# identical for both experts (joint attention, zip(strict=True)).
_W = int(os.environ.get("PI05_TINY_WIDTH", "64"))  # e.g. 256 -> ~1.5M params
TINY_GEMMA = {
    "gemma_2b": modeling_pi05.GemmaConfig(
        width=_W, depth=2, mlp_dim=2 * _W, num_heads=8, num_kv_heads=1, head_dim=8
    ),
    "gemma_300m": modeling_pi05.GemmaConfig(
        width=_W // 2, depth=2, mlp_dim=_W, num_heads=8, num_kv_heads=1, head_dim=8
    ),
}

_RealPaliGemma = modeling_pi05.PaliGemmaForConditionalGenerationWithPiGemma
_RealExpert = modeling_pi05.PiGemmaForCausalLM


class _TinyPaliGemma(_RealPaliGemma):
    """Shrinks the (already fully built) HF PaliGemma config right before the modules are made."""

    def __init__(self, config):
        vc, tc = config.vision_config, config.text_config
        vc.hidden_size, vc.intermediate_size = 32, 64
        vc.num_hidden_layers, vc.num_attention_heads = 2, 2
        vc.patch_size = TINY_PATCH
        vc.projection_dim = tc.hidden_size  # stock code hard-codes 2048 (modeling_pi05.py:217)
        tc.num_image_tokens = (vc.image_size // vc.patch_size) ** 2
        tc.vocab_size = TINY_VOCAB
        config.vocab_size = TINY_VOCAB
        config.image_token_index = TINY_VOCAB - 1
        super().__init__(config)


class _TinyExpert(_RealExpert):
    def __init__(self, config, **kw):
        config.vocab_size = TINY_VOCAB  # stock: 257152 -> an unused lm_head of 257152*width
        super().__init__(config, **kw)


@contextlib.contextmanager
def tiny_pi05():
    with (
        mock.patch.object(modeling_pi05, "get_gemma_config", lambda v: TINY_GEMMA[v]),
        mock.patch.object(modeling_pi05, "PaliGemmaForConditionalGenerationWithPiGemma", _TinyPaliGemma),
        mock.patch.object(modeling_pi05, "PiGemmaForCausalLM", _TinyExpert),
    ):
        yield


CAMS = ["observation.images.cam0", "observation.images.cam1"]
STATE_DIM, ACT_DIM, CHUNK, B = 6, 6, 4, 2


def make_config(**kw):
    cfg = PI05Config(
        device="cpu",
        dtype="float32",
        chunk_size=CHUNK,
        n_action_steps=CHUNK,
        max_state_dim=8,
        max_action_dim=8,
        image_resolution=(TINY_IMG, TINY_IMG),
        tokenizer_max_length=96,
        num_inference_steps=2,
        **kw,
    )
    cfg.input_features = {
        c: PolicyFeature(type=FeatureType.VISUAL, shape=(3, TINY_IMG, TINY_IMG)) for c in CAMS
    }
    cfg.input_features["observation.state"] = PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,))
    cfg.output_features = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(ACT_DIM,))}
    return cfg


# ----------------------------------------------------------------------------------------------
# 2. Tiny offline Gemma tokenizer (byte-fallback BPE, no sentencepiece) saved for AutoTokenizer
# ----------------------------------------------------------------------------------------------
def build_tokenizer():
    from transformers import AutoTokenizer, GemmaTokenizer

    vocab = {"<pad>": 0, "<eos>": 1, "<bos>": 2, "<unk>": 3, "<mask>": 4}
    for b in range(256):
        vocab[f"<0x{b:02X}>"] = len(vocab)
    for ch in ["▁"] + [chr(c) for c in range(33, 127)]:
        vocab.setdefault(ch, len(vocab))
    assert len(vocab) <= TINY_VOCAB
    tok = GemmaTokenizer(vocab=vocab, merges=[], add_bos_token=True)  # PaliGemma prepends <bos>
    if TOK_DIR.exists():
        shutil.rmtree(TOK_DIR)
    tok.save_pretrained(TOK_DIR)
    tok2 = AutoTokenizer.from_pretrained(str(TOK_DIR))  # offline, local dir
    ids = tok2("Task: pick cube, State: 1 2;\nAction: ")["input_ids"]
    print(
        f"[tok] saved files={sorted(p.name for p in TOK_DIR.iterdir())} class={type(tok2).__name__} "
        f"len={len(tok2)} ids[:12]={ids[:12]} roundtrip={tok2.decode(ids, skip_special_tokens=True)!r}"
    )
    return tok2


def fake_stats():
    def s(d):
        return {
            "mean": torch.zeros(d),
            "std": torch.ones(d),
            "min": -torch.ones(d),
            "max": torch.ones(d),
            "q01": -torch.ones(d),
            "q99": torch.ones(d),
            "q10": -0.8 * torch.ones(d),
            "q90": 0.8 * torch.ones(d),
        }

    return {"observation.state": s(STATE_DIM), "action": s(ACT_DIM)}


def make_processors(cfg):
    real = processor_pi05.TokenizerProcessorStep

    def tok_step(**kw):
        kw["tokenizer_name"] = str(TOK_DIR)  # replaces "google/paligemma-3b-pt-224" (processor_pi05.py:141)
        return real(**kw)

    with mock.patch.object(processor_pi05, "TokenizerProcessorStep", tok_step):
        return processor_pi05.make_pi05_pre_post_processors(cfg, dataset_stats=fake_stats())


def raw_batch(seed=0):
    g = torch.Generator().manual_seed(seed)
    b = {c: torch.rand(B, 3, TINY_IMG, TINY_IMG, generator=g) for c in CAMS}
    b["observation.state"] = torch.rand(B, STATE_DIM, generator=g) * 2 - 1
    b["action"] = torch.rand(B, CHUNK, ACT_DIM, generator=g) * 2 - 1
    b["task"] = ["pick the red cube", "go"]
    return b


# ----------------------------------------------------------------------------------------------
# 3. Attention capture by swapping modeling_gemma.eager_attention_forward
# ----------------------------------------------------------------------------------------------
class AttnCapture:
    def __init__(self, n_img_keys, chunk, clone=True, skip_recompute=True):
        self.n_img_keys, self.chunk, self.clone, self.skip_recompute = (
            n_img_keys,
            chunk,
            clone,
            skip_recompute,
        )
        self.active = False
        self.slices = []
        self.calls = 0
        self.recompute_calls = 0
        self.shapes = set()
        self._orig = modeling_gemma.eager_attention_forward

    def __call__(self, module, query, key, value, attention_mask, scaling, dropout=0.0, **kw):
        out, w = self._orig(module, query, key, value, attention_mask, scaling, dropout=dropout, **kw)
        if self.active:
            self.calls += 1
            in_backward = torch._C._current_graph_task_id() != -1  # checkpoint recomputation
            if in_backward:
                self.recompute_calls += 1
            if not (in_backward and self.skip_recompute):
                self.shapes.add((tuple(query.shape), tuple(key.shape), tuple(w.shape)))
                sl = w[:, :, -self.chunk :, : self.n_img_keys]  # action-query rows x image-key cols
                self.slices.append(sl.clone() if self.clone else sl)
        return out, w

    @contextlib.contextmanager
    def capturing(self):
        self.slices, self.active = [], True
        with mock.patch.object(modeling_gemma, "eager_attention_forward", self):
            try:
                yield self
            finally:
                self.active = False


def attn_loss(slices, n_per_cam):
    # toy grounding loss: -log(attention mass of action queries on camera-0 patches), mean over layers
    a = torch.stack([s.float() for s in slices[: len(slices)]], 0)  # (L, B, H, chunk, n_img)
    mass = a[..., :n_per_cam].sum(-1)
    return -(mass + 1e-6).log().mean()


def rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main():
    print(f"torch {torch.__version__} threads={torch.get_num_threads()} rss0={rss_mb():.0f}MB")
    build_tokenizer()

    cfg = make_config()
    with tiny_pi05():
        policy = PI05Policy(cfg)
    n_params = sum(p.numel() for p in policy.parameters())
    n_sd = len(policy.state_dict())
    pg = policy.model.paligemma_with_expert
    print(
        f"[model] params={n_params:,} state_dict_keys={n_sd} "
        f"vision_tokens/cam={pg.paligemma.config.text_config.num_image_tokens} "
        f"proj={tuple(pg.paligemma.model.multi_modal_projector.linear.weight.shape)} "
        f"attn_impl={pg.paligemma.model.language_model.config._attn_implementation}"
    )

    pre, post = make_processors(cfg)
    batch = pre(raw_batch())
    print(
        "[pre] keys/shapes:",
        {
            k: (tuple(v.shape), str(v.dtype)) if torch.is_tensor(v) else type(v).__name__
            for k, v in batch.items()
        },
    )
    tok_step = [s for s in pre.steps if type(s).__name__ == "TokenizerProcessorStep"][0]
    print("[pre] tokenizer step config:", tok_step.get_config())
    ntok = batch["observation.language.tokens"].shape[1]
    print("[pre] n valid tokens per sample:", batch["observation.language.attention_mask"].sum(1).tolist())

    # ---- training forward + backward, timing ----
    policy.train()
    for i in range(3):
        t0 = time.perf_counter()
        loss, info = policy.forward(batch)
        loss.backward()
        dt = time.perf_counter() - t0
        policy.zero_grad(set_to_none=True)
        print(f"[train] iter {i} loss={loss.item():.4f} fwd+bwd={dt:.3f}s rss_peak={rss_mb():.0f}MB")

    # ---- select_action ----
    policy.reset()
    obs = {k: v for k, v in batch.items() if k != "action"}
    t0 = time.perf_counter()
    a = policy.select_action(obs)
    a_post = post(a)
    print(
        f"[select_action] action={tuple(a.shape)} post={tuple(a_post.shape)} dt={time.perf_counter() - t0:.3f}s "
        f"queue_left={len(policy._action_queue)}"
    )

    # ---- attention capture: no-GC vs GC ----
    n_per_cam = (TINY_IMG // TINY_PATCH) ** 2
    n_img = n_per_cam * len(CAMS)
    L = n_img + ntok + CHUNK
    print(f"[layout] seq = [cam0 {n_per_cam} | cam1 {n_per_cam} | lang {ntok} | action {CHUNK}] = {L}")

    probe = [
        "model.paligemma_with_expert.gemma_expert.model.layers.0.self_attn.q_proj.weight",
        "model.paligemma_with_expert.paligemma.model.language_model.layers.1.self_attn.k_proj.weight",
        "model.paligemma_with_expert.paligemma.model.vision_tower.vision_model.embeddings.patch_embedding.weight",
        "model.paligemma_with_expert.paligemma.model.multi_modal_projector.linear.weight",
        "model.action_in_proj.weight",
        "model.time_mlp_in.weight",
    ]
    params = dict(policy.named_parameters())
    # adaRMS `dense` layers are zero-initialised (pi_gemma.py:98-99) -> d/d(time_mlp) == 0 at init; perturb them
    with torch.no_grad():
        for n_, p_ in params.items():
            if ".dense." in n_:
                p_.normal_(0, 0.02)

    def run(gc, clone=True, skip_recompute=True, lam=1.0):
        if gc:
            policy.model.gradient_checkpointing_enable()
        else:
            policy.model.gradient_checkpointing_disable()
        policy.train()
        policy.zero_grad(set_to_none=True)
        cap = AttnCapture(n_img, CHUNK, clone=clone, skip_recompute=skip_recompute)
        torch.manual_seed(123)
        t0 = time.perf_counter()
        with cap.capturing():
            flow, _ = policy.forward(batch)
            la = attn_loss(cap.slices, n_per_cam)
            (flow + lam * la).backward()
        dt = time.perf_counter() - t0
        grads = {k: params[k].grad.detach().clone() if params[k].grad is not None else None for k in probe}
        return dict(flow=flow.item(), attn=la.item(), grads=grads, cap=cap, dt=dt)

    r0 = run(gc=False)
    r1 = run(gc=True)
    r2 = run(gc=True, skip_recompute=False)
    r3 = run(gc=True, clone=False)
    for name, r in [("noGC", r0), ("GC", r1), ("GC keep-recompute", r2), ("GC view", r3)]:
        c = r["cap"]
        print(
            f"[capture {name}] flow={r['flow']:.6f} attn={r['attn']:.6f} calls={c.calls} "
            f"recompute_calls={c.recompute_calls} stored={len(c.slices)} dt={r['dt']:.3f}s shapes={sorted(c.shapes)}"
        )
    print(
        "[grad norms noGC]",
        {
            k.split(".")[-3] + "." + k.split(".")[-2]: round(float(v.norm()), 5)
            for k, v in r0["grads"].items()
        },
    )
    for name, r in [("GC", r1), ("GC keep-recompute", r2), ("GC view", r3)]:
        diffs = {}
        for k in probe:
            g0, g1 = r0["grads"][k], r["grads"][k]
            diffs[k.split("model.", 1)[1][-60:]] = (
                None if g0 is None or g1 is None else float((g0 - g1).abs().max() / (g0.abs().max() + 1e-12))
            )
        print(
            f"[grad rel-diff noGC vs {name}] dloss={abs(r0['flow'] - r['flow']) + abs(r0['attn'] - r['attn']):.2e}"
        )
        for k, v in diffs.items():
            print(f"    {k}: {v}")

    # attention-only gradient reaches the vision tower / expert?
    policy.model.gradient_checkpointing_disable()
    policy.zero_grad(set_to_none=True)
    cap = AttnCapture(n_img, CHUNK)
    torch.manual_seed(123)
    with cap.capturing():
        policy.forward(batch)
        attn_loss(cap.slices, n_per_cam).backward()
    print(
        "[attn-only grads] ",
        {
            k.split(".")[-3] + "." + k.split(".")[-2]: float(params[k].grad.abs().sum())
            if params[k].grad is not None
            else None
            for k in probe
        },
    )
    # row sums sanity: full rows sum to 1, slice mass over image keys
    s0 = cap.slices[0]
    print(
        f"[slice] shape={tuple(s0.shape)} mass_on_images(mean)={s0.sum(-1).mean():.3f} "
        f"mass_on_cam1={s0[..., n_per_cam:].sum(-1).mean():.3f} "
        f"clone_storage={s0.untyped_storage().nbytes()}B"
    )
    cap_v = AttnCapture(n_img, CHUNK, clone=False)
    torch.manual_seed(123)
    with cap_v.capturing():
        policy.forward(batch)
    print(
        f"[slice] view keeps base alive: view storage={cap_v.slices[0].untyped_storage().nbytes()}B "
        f"(= B*H*L*L*4 = {B * 8 * L * L * 4})"
    )
    # padded language keys & missing camera get exactly zero attention
    cap_full = AttnCapture(L, L)  # full matrix
    torch.manual_seed(123)
    no_cam1 = {k: v for k, v in batch.items() if k != CAMS[1]}
    with cap_full.capturing():
        policy.forward(no_cam1)
    w = cap_full.slices[0]
    lang_mask = batch["observation.language.attention_mask"]
    pad_cols = (~lang_mask[1]).nonzero().flatten() + n_img
    print(
        f"[mask] full weights {tuple(w.shape)}; row sums={w.sum(-1).mean():.4f}; action rows -> cam1 (missing) "
        f"mass={w[:, :, -CHUNK:, n_per_cam:n_img].sum(-1).max():.2e}; sample1 padded-lang mass="
        f"{w[1, :, -CHUNK:, pad_cols].sum(-1).max():.2e}; prefix rows -> action keys mass="
        f"{w[:, :, :n_per_cam, -CHUNK:].sum(-1).max():.2e} (valid cam0 rows; fully-masked pad rows become uniform)"
    )

    # capture at inference (prefix pass via GemmaAttention, denoise via GemmaAttention with KV cache)
    cap = AttnCapture(n_img, CHUNK)
    policy.eval()
    with cap.capturing(), torch.no_grad():
        policy.predict_action_chunk(obs)
    print(f"[inference capture] calls={cap.calls} shapes={sorted(cap.shapes)}")

    # ---- save / reload (checkpoint dir with symlinked weights) ----
    ck = OUT / "ckpt_real"
    link = OUT / "ckpt_link"
    for d in (ck, link):
        shutil.rmtree(d, ignore_errors=True)
    policy.save_pretrained(ck)
    pre.save_pretrained(ck)
    post.save_pretrained(ck)
    link.mkdir()
    for f in ck.iterdir():
        (link / f.name).symlink_to(f)  # every file a symlink, incl. model.safetensors
    print("[ckpt] files:", sorted(p.name for p in ck.iterdir()))
    print(
        "[ckpt] tokenizer step json:",
        [
            s
            for s in json.load(open(ck / "policy_preprocessor.json"))["steps"]
            if "tokenizer" in s["registry_name"]
        ],
    )

    from lerobot.configs import PreTrainedConfig
    from lerobot.policies.factory import make_pre_post_processors

    cfg2 = PreTrainedConfig.from_pretrained(link)
    cfg2.pretrained_path = link
    with tiny_pi05():
        p2 = PI05Policy.from_pretrained(link, config=cfg2)
    sd1, sd2 = policy.state_dict(), p2.state_dict()
    same = all(torch.equal(sd1[k], sd2[k]) for k in sd1) and sd1.keys() == sd2.keys()
    print(f"[ckpt] reload through symlinks: type={cfg2.type} identical_weights={same}")
    pre2, post2 = make_pre_post_processors(
        cfg2,
        pretrained_path=str(link),
        dataset_stats=fake_stats(),
        preprocessor_overrides={
            "device_processor": {"device": "cpu"},
            "normalizer_processor": {
                "features": {**cfg2.input_features, **cfg2.output_features},
                "norm_map": cfg2.normalization_mapping,
                "stats": fake_stats(),
            },
            "rename_observations_processor": {"rename_map": {}},
        },
        postprocessor_overrides={
            "unnormalizer_processor": {
                "features": cfg2.output_features,
                "norm_map": cfg2.normalization_mapping,
                "stats": fake_stats(),
            }
        },
    )
    b2 = pre2(raw_batch())
    print(
        f"[ckpt] reloaded preprocessor tokens equal: {torch.equal(b2['observation.language.tokens'], batch['observation.language.tokens'])}"
    )

    # ---- "starting checkpoint" for a subclass type: rewrite config.json type, symlink the rest ----
    from dataclasses import dataclass as _dc

    @PreTrainedConfig.register_subclass("pi05_grounded_probe")
    @_dc
    class PI05GroundedProbeConfig(PI05Config):
        attn_reg_weight: float = 0.1

    class PI05GroundedProbePolicy(PI05Policy):
        config_class = PI05GroundedProbeConfig
        name = "pi05_grounded_probe"

    gdir = OUT / "ckpt_grounded"
    shutil.rmtree(gdir, ignore_errors=True)
    gdir.mkdir()
    for f in ck.iterdir():
        if f.name != "config.json":
            (gdir / f.name).symlink_to(f)
    cj = json.load(open(ck / "config.json"))
    cj["type"] = "pi05_grounded_probe"
    json.dump(cj, open(gdir / "config.json", "w"), indent=2)
    cfg3 = PreTrainedConfig.from_pretrained(gdir)
    with tiny_pi05(), contextlib.redirect_stdout(open(os.devnull, "w")):
        p3 = PI05GroundedProbePolicy.from_pretrained(gdir, config=cfg3)
    sd3 = p3.state_dict()
    print(
        f"[ckpt] retyped dir -> {type(cfg3).__name__} attn_reg_weight={cfg3.attn_reg_weight} "
        f"identical_weights={sd3.keys() == sd1.keys() and all(torch.equal(sd1[k], sd3[k]) for k in sd1)}"
    )
    # broken weights symlink: PI05Policy.from_pretrained silently returns a randomly initialised model
    bdir = OUT / "ckpt_broken"
    shutil.rmtree(bdir, ignore_errors=True)
    bdir.mkdir()
    (bdir / "config.json").symlink_to(ck / "config.json")
    (bdir / "model.safetensors").symlink_to(OUT / "does_not_exist.safetensors")
    import io

    buf = io.StringIO()
    with tiny_pi05(), contextlib.redirect_stdout(buf):
        p4 = PI05Policy.from_pretrained(bdir, config=PreTrainedConfig.from_pretrained(bdir))
    same4 = all(torch.equal(sd1[k], p4.state_dict()[k]) for k in sd1)
    print(
        f"[ckpt] broken symlink -> no exception, identical_weights={same4}; printed: "
        f"{[l for l in buf.getvalue().splitlines() if 'Could not' in l or 'Returning' in l]}"
    )
    print(f"[done] peak RSS {rss_mb():.0f}MB")


if __name__ == "__main__":
    main()
