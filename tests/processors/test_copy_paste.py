"""The copy-paste distractor step: masks, sprites, gating, determinism, checkpoint round trip.

Most tests use a small synthetic sprite bank (no MuJoCo); one renders the real bank.
"""

import pytest
import torch
from hypothesis import HealthCheck, given, settings, strategies as st
from lerobot.processor import PolicyProcessorPipeline
from lerobot.processor.converters import batch_to_transition, transition_to_batch
from lerobot.processor.pipeline import ProcessorStepRegistry, TransitionKey

from lerobot_condground.core.labels import SYNTHETIC_DISTRACTOR, TARGET_OBJECT, TARGET_RECEPTACLE
from lerobot_condground.processors.copy_paste import CopyPasteDistractorStep

CAM, SEG = "observation.images.top", "observation.segmentation"


def fake_bank(side: int = 21) -> torch.Tensor:
    """8 sprites (4 object, 4 receptacle shapes): discs and squares of a few sizes, shaded."""
    ys, xs = torch.meshgrid(torch.arange(side) - side // 2, torch.arange(side) - side // 2, indexing="ij")
    sprites = []
    for k in range(8):
        radius = 3 + k
        alpha = ((xs**2 + ys**2) <= radius**2) if k % 2 else ((xs.abs() <= radius) & (ys.abs() <= radius))
        alpha = alpha.float()
        shading = alpha * (0.6 + 0.4 * (xs + side) / (2 * side))
        sprites.append(torch.stack([shading, alpha]))
    return torch.stack(sprites)


def make_step(**kw) -> CopyPasteDistractorStep:
    step = CopyPasteDistractorStep(**kw)
    step.load_state_dict(
        {"sprites": fake_bank(), "generator_state": step._generator.get_state(), "batches": torch.tensor(0)}
    )
    return step


def scene(batch: int = 4, height: int = 48, width: int = 64, seed: int = 0):
    """Frames with a red target object and a blue receptacle, as label maps the recorder writes."""
    g = torch.Generator().manual_seed(seed)
    images = 0.5 + 0.05 * torch.rand(batch, 3, height, width, generator=g)
    seg = torch.zeros(batch, height, width, dtype=torch.int64)
    seg[:, height // 4 : height // 4 + 5, width // 4 : width // 4 + 5] = TARGET_OBJECT
    seg[:, height // 2 : height // 2 + 12, width // 2 : width // 2 + 12] = TARGET_RECEPTACLE
    images = torch.where(
        (seg == TARGET_OBJECT).unsqueeze(1), torch.tensor([0.85, 0.12, 0.1]).view(1, 3, 1, 1), images
    )
    images = torch.where(
        (seg == TARGET_RECEPTACLE).unsqueeze(1), torch.tensor([0.1, 0.3, 0.85]).view(1, 3, 1, 1), images
    )
    return images, seg


def check_invariants(step, images, seg, out, out_seg):
    assert out.shape == images.shape and out.dtype == images.dtype
    assert out_seg.shape == seg.shape and out_seg.dtype == seg.dtype
    assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    synthetic = out_seg == SYNTHETIC_DISTRACTOR
    # The frame changes only under the synthetic-distractor label, and other labels are untouched.
    assert not (out != images).any(1)[~synthetic].any()
    assert torch.equal(out_seg[~synthetic], seg[~synthetic])
    # Pastes cover at most max_occlusion of each target's visible pixels.
    for label in (TARGET_OBJECT, TARGET_RECEPTACLE):
        target = seg == label
        covered = (target & synthetic).flatten(1).sum(1)
        assert (covered <= step.max_occlusion * target.flatten(1).sum(1) + 1e-6).all()


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    batch=st.integers(1, 4),
    height=st.integers(4, 40),
    width=st.integers(4, 40),
    boxes=st.lists(
        st.tuples(st.integers(1, 2), st.floats(0, 1), st.floats(0, 1), st.floats(0, 1), st.floats(0, 1)),
        max_size=4,
    ),
    max_occlusion=st.sampled_from([0.0, 0.1, 0.5, 1.0]),
    sprite_scale=st.sampled_from([0.2, 1.0, 3.0]),
    seed=st.integers(0, 2**16),
)
def test_masks_and_sprites_of_any_shape(batch, height, width, boxes, max_occlusion, sprite_scale, seed):
    """Any size, empty targets, targets touching borders or covering the whole frame."""
    g = torch.Generator().manual_seed(seed)
    images = torch.rand(batch, 3, height, width, generator=g)
    seg = torch.zeros(batch, height, width, dtype=torch.int64)
    for label, y0, x0, y1, x1 in boxes:
        ya, yb = sorted((int(y0 * height), int(y1 * height) + 1))
        xa, xb = sorted((int(x0 * width), int(x1 * width) + 1))
        seg[:, ya:yb, xa:xb] = label
    step = make_step(
        prob=1.0,
        max_occlusion=max_occlusion,
        sprite_scale=sprite_scale,
        seed=seed,
        placement_box=[0.0, 0.0, 1.0, 1.0],
    )
    out, out_seg = step.augment(images, seg)
    check_invariants(step, images, seg, out, out_seg)


def test_pastes_and_falls_back_when_targets_are_absent():
    step = make_step(prob=1.0, min_count=4, max_count=4, max_occlusion=0.0)
    images, seg = scene()
    out, out_seg = step.augment(images, seg)
    check_invariants(step, images, seg, out, out_seg)
    assert ((out_seg == SYNTHETIC_DISTRACTOR).flatten(1).sum(1) > 0).all()
    # No target visible: same_color/same_shape have nothing to copy and fall back to neither.
    empty = torch.zeros_like(seg)
    for category in ("same_color", "same_shape"):
        out, out_seg = make_step(prob=1.0, categories=[category]).augment(images, empty)
        check_invariants(step, images, empty, out, out_seg)
        assert (out_seg == SYNTHETIC_DISTRACTOR).any()


def test_same_color_matches_the_target_median_and_same_shape_copies_its_mask():
    images, seg = scene(batch=1, height=64, width=96)
    seg[:, :, : 96 // 2] = torch.where(seg[:, :, :48] == TARGET_RECEPTACLE, 0, seg[:, :, :48])
    out, out_seg = make_step(
        prob=1.0, min_count=1, max_count=1, categories=["same_color"], max_occlusion=0.0, seed=3
    ).augment(images, seg)
    pasted = out[0][:, out_seg[0] == SYNTHETIC_DISTRACTOR]
    target_color = images[0][:, seg[0] == TARGET_OBJECT].median(1).values
    receptacle_color = images[0][:, seg[0] == TARGET_RECEPTACLE].median(1).values
    median = pasted.median(1).values
    assert min((median - target_color).abs().max(), (median - receptacle_color).abs().max()) < 0.08
    out, out_seg = make_step(
        prob=1.0, min_count=1, max_count=1, categories=["same_shape"], max_occlusion=0.0, seed=3
    ).augment(images, seg)
    size = int((out_seg == SYNTHETIC_DISTRACTOR).sum())
    # A rotated copy of the 5x5 object or 12x12 receptacle, possibly clipped at the frame's edge.
    assert 0 < size <= 12 * 12 * 1.3


def test_unbatched_and_bad_inputs():
    step = make_step(prob=1.0)
    images, seg = scene(batch=1)
    out, out_seg = step.augment(images[0], seg[0])
    assert out.shape == images[0].shape and out_seg.shape == seg[0].shape
    with pytest.raises(ValueError, match="float frames"):
        step.augment((images * 255).to(torch.uint8), seg)
    with pytest.raises(ValueError, match="label map"):
        step.augment(images, seg[:, :-1])
    with pytest.raises(KeyError, match=SEG):
        step({TransitionKey.OBSERVATION: {CAM: images}, TransitionKey.ACTION: torch.zeros(1, 7)})


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"prob": 1.5}, "prob"),
        ({"min_count": 5, "max_count": 4}, "min_count"),
        ({"max_count": 0}, "max_count"),
        ({"max_occlusion": -0.1}, "max_occlusion"),
        ({"categories": ["same_size"]}, "categories"),
        ({"categories": []}, "categories"),
        ({"seed": -1}, "seed"),
        ({"sprite_scale": 0}, "sprite_scale"),
        ({"camera_key": ""}, "camera_key"),
        ({"placement_box": [0.5, 0, 0.2, 1]}, "placement_box"),
        ({"max_count": True}, "max_count"),
        ({"warmup_steps": -1}, "warmup_steps"),
        ({"roles": ["object", "object"]}, "roles"),
        ({"roles": ["bin"]}, "roles"),
    ],
)
def test_fields_are_validated(kwargs, name):
    with pytest.raises(ValueError, match=f"{name}=.*allowed"):
        CopyPasteDistractorStep(**kwargs)


def test_gate_training_only():
    """No-op without action and under no_grad; changes frames with action and grad."""
    step = make_step(prob=1.0)
    images, seg = scene()
    obs = {CAM: images, SEG: seg, "observation.state": torch.zeros(4, 7)}
    rollout = step({TransitionKey.OBSERVATION: obs})
    assert rollout[TransitionKey.OBSERVATION][CAM] is images
    with torch.no_grad():
        held_out = step({TransitionKey.OBSERVATION: obs, TransitionKey.ACTION: torch.zeros(4, 7)})
    assert held_out[TransitionKey.OBSERVATION][CAM] is images
    trained = step({TransitionKey.OBSERVATION: obs, TransitionKey.ACTION: torch.zeros(4, 7)})
    new_obs = trained[TransitionKey.OBSERVATION]
    assert not torch.equal(new_obs[CAM], images) and (new_obs[SEG] == SYNTHETIC_DISTRACTOR).any()
    assert new_obs["observation.state"] is obs["observation.state"]
    assert torch.equal(obs[CAM], scene()[0])  # the caller's batch is not modified in place


def test_deterministic_under_a_seed_and_resumes_the_sequence():
    images, seg = scene()
    a, b, c = make_step(seed=7), make_step(seed=7), make_step(seed=8)
    first_a, first_b = a.augment(images, seg), b.augment(images, seg)
    assert all(torch.equal(x, y) for x, y in zip(first_a, first_b))
    assert not torch.equal(first_a[0], c.augment(images, seg)[0])
    resumed = make_step(seed=0)
    resumed.load_state_dict(a.state_dict())
    assert all(torch.equal(x, y) for x, y in zip(a.augment(images, seg), resumed.augment(images, seg)))


def test_roles_choose_whose_look_alikes_are_pasted():
    """roles=[object] pastes copies of the 5x5 object only, roles=[receptacle] of the 12x12 receptacle only."""
    images, seg = scene(batch=32)
    sizes = {}
    for role in ("object", "receptacle"):
        step = make_step(prob=1.0, max_count=1, max_occlusion=1.0, categories=["same_shape"], roles=[role])
        pasted = (step.augment(images, seg)[1] == SYNTHETIC_DISTRACTOR).flatten(1).sum(1)
        sizes[role] = pasted[pasted > 0]
    assert len(sizes["object"]) > 16 and len(sizes["receptacle"]) > 16
    assert sizes["object"].max() <= 40 < 100 <= sizes["receptacle"].min()


def test_warmup_ramps_the_paste_probability_and_resumes_it():
    """warmup_steps: no pastes in the first training batch, about prob/2 of the samples halfway, prob after;
    the batch count travels with the saved state, and a state without it is refused under a warmup."""
    images, seg = scene(batch=64)
    obs = {CAM: images, SEG: seg}
    action = torch.zeros(64, 7)

    def augmented_share(step):
        out = step({TransitionKey.OBSERVATION: obs, TransitionKey.ACTION: action})[TransitionKey.OBSERVATION]
        return (out[SEG] == SYNTHETIC_DISTRACTOR).flatten(1).any(1).float().mean().item()

    step = make_step(prob=1.0, min_count=1, max_occlusion=1.0, sprite_scale=4.0, warmup_steps=4)
    assert step.current_prob() == 0.0 and augmented_share(step) == 0.0
    step({TransitionKey.OBSERVATION: obs, TransitionKey.ACTION: action})
    assert step.current_prob() == 0.5 and 0.3 < augmented_share(step) < 0.7
    with torch.no_grad():  # held-out batches neither paste nor count
        step({TransitionKey.OBSERVATION: obs, TransitionKey.ACTION: action})
    assert step.current_prob() == 0.75
    resumed = make_step(prob=1.0, min_count=1, max_occlusion=1.0, sprite_scale=4.0, warmup_steps=4)
    resumed.load_state_dict(step.state_dict())
    assert resumed.current_prob() == 0.75
    augmented_share(resumed)
    assert resumed.current_prob() == 1.0 and augmented_share(resumed) == 1.0
    # Offline augmentation (`condground augment`) has no batches to ramp over: always `prob`.
    assert (
        step.current_prob() < 1.0
        and (step.augment(images, seg)[1] == SYNTHETIC_DISTRACTOR).flatten(1).any(1).all()
    )
    state = step.state_dict()
    del state["batches"]
    with pytest.raises(ValueError, match="warmup_steps=4 .*no batch count.*allowed: warmup_steps=0"):
        make_step(warmup_steps=4).load_state_dict(state)
    make_step().load_state_dict(state)


def test_registered_and_config_round_trip():
    assert ProcessorStepRegistry.get("condground_copy_paste") is CopyPasteDistractorStep
    step = CopyPasteDistractorStep(
        prob=0.5,
        min_count=2,
        max_count=3,
        max_occlusion=0.2,
        seed=4,
        categories=["neither"],
        camera_key="observation.images.wrist",
        warmup_steps=100,
        roles=["receptacle"],
    )
    assert CopyPasteDistractorStep(**step.get_config()).get_config() == step.get_config()
    assert step._bank is None  # construction never renders


def test_pipeline_save_load_round_trip(tmp_path):
    """save_pretrained/from_pretrained keeps config, sprites and generator: identical outputs, no MuJoCo."""
    step = make_step(prob=1.0, seed=5, max_count=3)
    pipeline = PolicyProcessorPipeline(
        steps=[step],
        name="policy_preprocessor",
        to_transition=batch_to_transition,
        to_output=transition_to_batch,
    )
    images, seg = scene()
    batch = {CAM: images, SEG: seg, "action": torch.zeros(4, 7)}
    pipeline(batch)  # advance the generator: the reloaded step must continue from here
    pipeline.save_pretrained(tmp_path)
    loaded = PolicyProcessorPipeline.from_pretrained(
        tmp_path,
        config_filename="policy_preprocessor.json",
        to_transition=batch_to_transition,
        to_output=transition_to_batch,
    )
    restored = loaded.steps[0]
    assert isinstance(restored, CopyPasteDistractorStep) and restored.get_config() == step.get_config()
    assert torch.equal(restored._bank, step._bank)
    expected, got = pipeline(batch), loaded(batch)
    assert torch.equal(expected[CAM], got[CAM]) and torch.equal(expected[SEG], got[SEG])
    assert not torch.equal(got[CAM], images)


def test_rendered_sprite_bank():
    """The real bank: MuJoCo renders the 8 augmentation shapes, rescaled to the frames."""
    step = CopyPasteDistractorStep(prob=1.0, seed=1)
    state = step.state_dict()
    bank = state["sprites"]
    assert bank.shape[:2] == (8, 2) and bank.shape[2] == bank.shape[3]
    area = (bank[:, 1] > 0.5).flatten(1).sum(1)
    assert (area > 20).all() and (area[4:].min() > area[:4].max())  # receptacles are larger than objects
    assert ((bank[:, 0] > 0) == (bank[:, 1] > 0)).all()  # shading only under alpha
    images, seg = scene(batch=2, height=120, width=160)
    out, out_seg = step.augment(images, seg)
    check_invariants(step, images, seg, out, out_seg)
    assert (out_seg == SYNTHETIC_DISTRACTOR).any()
