"""Label features: lossless PNG encoding and the decoding step of act_modified's preprocessor."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays

from lerobot_condground.core.labels import (
    OBS_PHASE,
    OBS_PROMPT_OBJECT,
    OBS_SEGMENTATION,
    decode_labels,
    decode_png,
    encode_png,
)
from lerobot_condground.processors.decode_labels import DecodeLabelsStep

shapes = st.one_of(
    st.tuples(st.integers(1, 40), st.integers(1, 40)),
    st.tuples(st.integers(1, 40), st.integers(1, 40), st.just(3)),
)


@settings(max_examples=60, deadline=None)
@given(shapes.flatmap(lambda shape: arrays(np.uint8, shape)))
def test_png_round_trip_is_lossless(image):
    decoded = decode_png(encode_png(image))
    assert decoded.dtype == np.uint8 and np.array_equal(decoded, image)


def test_rgb_is_stored_as_rgb():
    import base64

    import cv2

    red = np.zeros((4, 4, 3), np.uint8)
    red[..., 0] = 255
    stored = cv2.imdecode(np.frombuffer(base64.b64decode(encode_png(red)), np.uint8), cv2.IMREAD_COLOR)
    assert stored[0, 0].tolist() == [0, 0, 255]  # OpenCV reads BGR: a PNG viewer sees red


@pytest.mark.parametrize(
    "bad", [np.zeros((4, 4), np.int64), np.zeros((4, 4, 2), np.uint8), np.zeros(4, np.uint8)]
)
def test_encode_refuses_what_it_cannot_store_losslessly(bad):
    with pytest.raises(ValueError, match="uint8"):
        encode_png(bad)


def test_decode_labels_batches_strings_and_passes_tensors():
    seg = np.arange(12, dtype=np.uint8).reshape(3, 4)
    crop = torch.rand(2, 64, 64, 3) * 255  # prompts from the env are float tensors already
    batch = {
        OBS_SEGMENTATION: [encode_png(seg), encode_png(seg + 1)],
        OBS_PROMPT_OBJECT: crop,
        OBS_PHASE: torch.tensor([0, 1]),
    }
    out = DecodeLabelsStep().observation(batch)
    assert out[OBS_SEGMENTATION].dtype == torch.uint8 and out[OBS_SEGMENTATION].shape == (2, 3, 4)
    assert torch.equal(out[OBS_SEGMENTATION][1], torch.from_numpy(seg + 1))
    assert out[OBS_PROMPT_OBJECT] is crop and out[OBS_PHASE] is batch[OBS_PHASE]
    assert decode_labels({OBS_SEGMENTATION: encode_png(seg)})[OBS_SEGMENTATION].shape == (3, 4)
    assert isinstance(batch[OBS_SEGMENTATION], list), "the input dict must not change"


def test_decode_rejects_garbage():
    with pytest.raises(ValueError, match="not a base64 PNG"):
        decode_png("aGVsbG8=")


def test_decode_step_takes_only_label_keys_and_decodes_only_those():
    with pytest.raises(ValueError, match="observation.state"):
        DecodeLabelsStep(keys=["observation.state"])
    seg = encode_png(np.zeros((2, 2), np.uint8))
    out = DecodeLabelsStep(keys=[OBS_PROMPT_OBJECT]).observation({OBS_SEGMENTATION: [seg]})
    assert out[OBS_SEGMENTATION] == [seg]
