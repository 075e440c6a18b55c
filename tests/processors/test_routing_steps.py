"""`condground_rgb_cue` and `condground_instruction` on real recorded batches, on real env observations
through LeRobot's eval preprocessing, and saved and reloaded as part of a LeRobot pipeline."""

import numpy as np
import pytest
import torch
from lerobot.envs.utils import preprocess_observation
from lerobot.processor import PolicyProcessorPipeline

from lerobot_condground.core.labels import OBS_DESTINATION, OBS_SEGMENTATION, decode_png
from lerobot_condground.core.routing import DESTINATION, instruction
from lerobot_condground.envs.routing_env import InstrumentRoutingEnv
from lerobot_condground.processors.instruction import InstructionStep
from lerobot_condground.processors.rgb_cue import RgbCueStep

TOP, WRIST = "observation.images.top", "observation.images.wrist"


@pytest.fixture(scope="module")
def batch(routing_dataset):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("local/routing", root=routing_dataset)
    loader = torch.utils.data.DataLoader(
        ds, batch_size=6, shuffle=True, generator=torch.Generator().manual_seed(0)
    )
    return next(iter(loader))


def _pipeline(*steps):
    return PolicyProcessorPipeline(steps=list(steps), name="policy_preprocessor")


def test_the_cue_highlights_the_destination_and_nothing_else(batch):
    out = _pipeline(RgbCueStep())(dict(batch))
    labels = torch.from_numpy(np.stack([decode_png(s) for s in batch[OBS_SEGMENTATION]]))
    inside = (labels == DESTINATION).unsqueeze(1).expand_as(batch[TOP])
    assert inside.any()
    changed = (out[TOP] - batch[TOP]).abs() > 1e-6
    assert changed[inside].float().mean() > 0.9 and not changed[~inside].any()
    # Pulled towards the cue's yellow: red and green up, blue down, on average over the mask.
    mean_before, mean_after = (
        batch[TOP].permute(1, 0, 2, 3)[:, inside[:, 0]],
        out[TOP].permute(1, 0, 2, 3)[:, inside[:, 0]],
    )
    assert mean_after[0].mean() > mean_before[0].mean() and mean_after[2].mean() < mean_before[2].mean()
    assert (out[WRIST] != batch[WRIST]).any()  # the wrist camera from its own masks
    off = _pipeline(RgbCueStep(enabled=False))(dict(batch))
    assert torch.equal(off[TOP], batch[TOP]) and torch.equal(off[WRIST], batch[WRIST])


@pytest.mark.parametrize("cue", [True, False])
def test_the_env_sends_the_cue_or_hides_it_through_lerobot_eval_preprocessing(cue):
    env = InstrumentRoutingEnv(subgoal="route", cue=cue, observation_height=96, observation_width=128)
    raw, info = env.reset(seed=2)
    # What lerobot-eval does with a vector env's observation: batch, convert, rename.
    stacked = {
        "pixels": {k: v[None] for k, v in raw["pixels"].items()},
        **{k: v[None] for k, v in raw.items() if k != "pixels"},
    }
    observation = preprocess_observation(stacked)
    out = _pipeline(RgbCueStep())(dict(observation))
    changed = (out[TOP] != observation[TOP]).any()
    assert bool(changed) == cue
    env.close()


def test_the_cue_without_masks_is_an_error_naming_the_flags():
    image = torch.rand(1, 3, 96, 128)
    with pytest.raises(ValueError, match=r"--env.cue=true \(cue shown\) or --env.cue=false"):
        _pipeline(RgbCueStep())({TOP: image})


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"alpha": 0}, "alpha=0 is not allowed"),
        ({"color": [1, 2, 0]}, "color="),
        ({"cameras": {}}, "cameras={}"),
    ],
)
def test_bad_cue_settings_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        RgbCueStep(**kwargs)


def test_the_instruction_step_gives_either_form_and_leaves_other_strings_alone(batch):
    explicit = _pipeline(InstructionStep(form="explicit"))(dict(batch))
    sides = ["left" if int(d) == 0 else "right" for d in batch[OBS_DESTINATION].reshape(-1)]
    for before, after, side in zip(batch["task"], explicit["task"], sides, strict=True):
        if "highlighted" in before:
            assert after == before.replace("highlighted", side)
        else:
            assert after == before  # pick, inspect, home: one form
    back = _pipeline(InstructionStep(form="generic"))(dict(explicit))
    assert back["task"] == list(batch["task"])
    # At evaluation the env already gives the explicit text: no destination is needed.
    text = instruction("place", "explicit", "left")
    assert _pipeline(InstructionStep(form="explicit"))({"task": [text]})["task"] == [text]


def test_an_explicit_instruction_without_the_destination_is_an_error():
    with pytest.raises(ValueError, match="--env.instruction=explicit"):
        _pipeline(InstructionStep(form="explicit"))({"task": [instruction("route")]})
    with pytest.raises(ValueError, match="form='polite' is not allowed"):
        InstructionStep(form="polite")


def test_the_steps_are_saved_and_reloaded_by_name(tmp_path):
    pipeline = _pipeline(RgbCueStep(enabled=False, alpha=0.4), InstructionStep(form="explicit"))
    pipeline.save_pretrained(tmp_path)
    loaded = PolicyProcessorPipeline.from_pretrained(tmp_path, config_filename="policy_preprocessor.json")
    cue, form = loaded.steps
    assert isinstance(cue, RgbCueStep) and not cue.enabled and cue.alpha == 0.4
    assert isinstance(form, InstructionStep) and form.form == "explicit"
