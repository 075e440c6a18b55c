"""No thread of the package stays at the real-time priority an AV1 encoder gives it (as root), nor any child.

SVT-AV1 moves the thread that runs it to SCHED_FIFO 99 when it may: these tests run the package's encoders for
real (the codec round trip, a recording) and look at the thread and at a child it launches afterwards."""

import os
import subprocess
import sys

import numpy as np
import pytest

from lerobot_condground.core.codec import video_roundtrip
from lerobot_condground.core.scheduling import kept_priority, normal_priority

pytestmark = pytest.mark.skipif(not hasattr(os, "sched_getscheduler"), reason="Linux scheduling policies")
CHILD = [sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"]


def frames() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 255, (6, 48, 64, 3), dtype=np.uint8)


def encode_raw() -> None:
    """LeRobot's encoder through PyAV with no guard: what every package encode site wraps."""
    import io

    import av

    with av.open(io.BytesIO(), "w", format="mp4") as container:
        stream = container.add_stream("libsvtav1", 20)
        stream.height, stream.width, stream.pix_fmt = 48, 64, "yuv420p"
        for frame in frames():
            container.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
        container.mux(stream.encode())


def test_the_encoder_raises_the_thread_where_it_may_and_kept_priority_undoes_it():
    normal_priority()
    with kept_priority():
        encode_raw()
    assert os.sched_getscheduler(0) == os.SCHED_OTHER
    encode_raw()
    raised = os.sched_getscheduler(0) != os.SCHED_OTHER
    normal_priority()
    assert os.sched_getscheduler(0) == os.SCHED_OTHER
    if os.geteuid() == 0:
        # The hazard itself, so the guards below are known to guard something here.
        assert raised, "SVT-AV1 no longer raises the thread as root: the guard may be dropped"


def test_codec_round_trip_leaves_the_thread_and_its_children_at_normal_priority():
    normal_priority()
    video_roundtrip(frames())
    assert os.sched_getscheduler(0) == os.SCHED_OTHER
    assert subprocess.run(CHILD, check=True, capture_output=True, text=True).stdout.strip() == "0"


def test_a_recording_leaves_the_thread_and_its_children_at_normal_priority(tmp_path):
    from lerobot_condground.cli import main

    normal_priority()
    flags = ["--env.task=PickPlaceFixedBin-v0", "--dataset.repo_id=local/prio", f"--dataset.root={tmp_path / 'ds'}",
             "--progress=false", "--dataset.num_episodes=1", "--env.observation_height=64",
             "--env.observation_width=80"]  # fmt: skip
    assert main(["record", *flags]) == 0
    assert os.sched_getscheduler(0) == os.SCHED_OTHER
    assert subprocess.run(CHILD, check=True, capture_output=True, text=True).stdout.strip() == "0"
