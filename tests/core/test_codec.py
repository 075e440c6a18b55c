"""The video round trip that makes raw renders look like a video dataset's frames, in the env and in the
copy-paste step: real LeRobot encoder settings, real MuJoCo frames."""

import numpy as np
import pytest
import torch

from lerobot_condground.core.codec import video_roundtrip
from lerobot_condground.core.configs import ConfigError, EvalEnvConfig
from lerobot_condground.core.labels import SYNTHETIC_DISTRACTOR, TARGET_OBJECT
from lerobot_condground.envs.configs import CondGroundEnvConfig
from lerobot_condground.processors.copy_paste import CopyPasteDistractorStep


def _cube_scene(seed: int = 1_000_000, codec: str = "none"):
    env = CondGroundEnvConfig(
        task="PickPlaceFixedBin-v0", observation_height=96, observation_width=128, camera_codec=codec
    ).make_env()
    obs, _ = env.reset(seed=seed)
    return obs["pixels"]["top"], env.unwrapped.render_segmentation()


def test_the_round_trip_blurs_and_desaturates_the_small_cube_and_leaves_the_background():
    frame, seg = _cube_scene()
    decoded = video_roundtrip(frame[None])[0]
    assert decoded.shape == frame.shape and decoded.dtype == np.uint8
    diff = np.abs(decoded.astype(float) - frame)
    cube, background = seg == TARGET_OBJECT, seg == 0
    assert cube.sum() > 5
    # The saturated 4-5 pixel cube loses most to 4:2:0 chroma; the large flat background almost nothing.
    assert diff[cube].mean() > 5 * diff[background].mean()
    assert np.median(decoded[cube][:, 0]) < np.median(frame[cube][:, 0])  # its red is washed out


def test_the_env_sends_frames_through_the_codec_when_asked():
    raw, _ = _cube_scene()
    coded, _ = _cube_scene(codec="video")
    assert not np.array_equal(raw, coded)
    np.testing.assert_array_equal(coded, video_roundtrip(raw[None])[0])


@pytest.mark.parametrize(
    "make, fragment",
    [
        (
            lambda: CondGroundEnvConfig(task="PickPlaceFixedBin-v0", camera_codec="h264"),
            "allowed: none, video",
        ),
        (
            lambda: CondGroundEnvConfig(
                task="PickPlaceFixedBin-v0",
                observation_height=97,
                observation_width=128,
                camera_codec="video",
            ),
            "even frame sizes",
        ),
        (lambda: EvalEnvConfig(camera_codec="av1"), "--env.camera_codec='av1'"),
        (lambda: CopyPasteDistractorStep(codec="jpeg"), "codec='jpeg'"),
        (lambda: video_roundtrip(np.zeros((1, 8, 8), np.uint8)), "(T, H, W, 3) uint8"),
    ],
)
def test_bad_codec_values_are_refused_with_the_value_named(make, fragment):
    with pytest.raises((ValueError, ConfigError)) as err:
        make()
    assert fragment in str(err.value)


def test_codec_pastes_are_coded_where_pasted_and_nowhere_else():
    frame, seg = _cube_scene()
    images = torch.from_numpy(frame).permute(2, 0, 1).float().div(255).unsqueeze(0).repeat(2, 1, 1, 1)
    labels = torch.from_numpy(seg.astype(np.int64)).unsqueeze(0).repeat(2, 1, 1)
    kwargs = dict(prob=1.0, min_count=2, max_count=2, seed=3)
    crisp, crisp_seg = CopyPasteDistractorStep(**kwargs).augment(images, labels)
    coded, coded_seg = CopyPasteDistractorStep(**kwargs, codec="video").augment(images, labels)
    assert torch.equal(crisp_seg, coded_seg)  # the same pastes, the same labels
    pasted = coded_seg == SYNTHETIC_DISTRACTOR
    assert pasted.any()
    near = torch.nn.functional.max_pool2d(pasted.unsqueeze(1).float(), 5, stride=1, padding=2)[:, 0] > 0
    changed = (coded != crisp).any(1)
    assert changed[pasted].float().mean() > 0.5  # the pastes carry the codec's error
    assert not changed[~near].any()  # the frame away from them is the decoded frame it was


def test_recording_refuses_a_second_codec_pass():
    from lerobot_condground.datasets.record import RecordConfig

    env = CondGroundEnvConfig(task="PickPlaceFixedBin-v0", camera_codec="video")
    with pytest.raises(ValueError, match="camera_codec='video' is not allowed when recording"):
        RecordConfig(env=env)
