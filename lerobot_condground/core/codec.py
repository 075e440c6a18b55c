"""A camera frame's trip through the video codec a LeRobotDataset stores it with.

A policy trained on a video dataset sees every frame after LeRobot's encoder (SVT-AV1, 4:2:0 chroma, CRF 30) and
decoder, and at evaluation the simulator's raw renders. At 96x128 the difference sits on the small saturated
objects a policy must tell apart: in Task 1's 200 drift demonstrations recorded as video and losslessly from the
same seeds, the target cube's 19 pixels differ by 34/13/21 (RGB, of 255) on average and its median colour moves
from (177, 35, 29) to (155, 43, 46), while the background differs by 2 (docs/policies.md, "What differs from
the paper"). `video_roundtrip` gives raw frames the same treatment, so the two can be made to
match: the env's `--env.camera_codec=video` (evaluation frames as the dataset stores them) and the copy-paste
step's `codec=video` (pasted look-alikes as blurred as the real objects they sit beside).
"""

from __future__ import annotations

import io
import os

import numpy as np

from lerobot_condground.core.scheduling import kept_priority

# none: frames as rendered (or pasted); video: through LeRobot's default RGB video encoder and back.
CAMERA_CODECS = ("none", "video")


def check_camera_codec(value, flag: str, height: int | None = None, width: int | None = None) -> None:
    """The codec's name, and with a frame size that 4:2:0 chroma can encode it (sizes unknown yet: name only)."""
    if value not in CAMERA_CODECS:
        raise ValueError(f"{flag}={value!r} is not allowed; allowed: {', '.join(CAMERA_CODECS)}")
    if value != "none" and height is not None and (height % 2 or width % 2):
        raise ValueError(f"{flag}={value!r} needs even frame sizes (4:2:0 chroma); got {height}x{width}")


def video_roundtrip(frames: np.ndarray, fps: int = 20) -> np.ndarray:
    """(T, H, W, 3) uint8 RGB frames -> the same frames encoded as one stream with LeRobot's default RGB encoder
    settings (those `condground record` and `lerobot-record` write) and decoded again, in memory."""
    import av
    from lerobot.configs.video import rgb_encoder_defaults

    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or not len(frames):
        raise ValueError(
            f"video_roundtrip takes (T, H, W, 3) uint8 frames, T >= 1; got {frames.dtype} {frames.shape}"
        )
    height, width = frames.shape[1:3]
    if height % 2 or width % 2:
        raise ValueError(
            f"frames of {height}x{width} cannot be 4:2:0 encoded; allowed: even heights and widths"
        )
    # SVT-AV1 prints a 20-line banner per encoder start; level 1 keeps its errors only (a user's value wins).
    os.environ.setdefault("SVT_LOG", "1")
    encoder = rgb_encoder_defaults()
    buffer = io.BytesIO()
    with kept_priority(), av.open(buffer, "w", format="mp4") as container:
        stream = container.add_stream(
            encoder.vcodec, fps, options=encoder.get_codec_options(1, as_strings=True)
        )
        stream.pix_fmt, stream.height, stream.width = encoder.pix_fmt, height, width
        for frame in frames:
            container.mux(
                stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24"))
            )
        container.mux(stream.encode())
    buffer.seek(0)
    with av.open(buffer) as container:
        decoded = np.stack([f.to_ndarray(format="rgb24") for f in container.decode(video=0)])
    if decoded.shape != frames.shape:
        raise RuntimeError(f"the video round trip returned {decoded.shape} frames for {frames.shape}")
    return decoded
