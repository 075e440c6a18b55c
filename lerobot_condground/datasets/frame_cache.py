"""Decoded video frames held in memory for a training run.

LeRobot decodes each sample's camera frames from the dataset's video files, for every sample of every
epoch (at 96x128 on a 2-core CPU about 2 ms of a sample's 6 ms of data loading). A run reads the same
frames every epoch, so while a `FrameCache` is active LeRobot's video query is
memoized per dataset root, episode and timestamps, up to a memory budget: the first epoch decodes,
later ones read memory, and the samples are the very tensors the decoder returned (tested).
"""

from __future__ import annotations

import functools

import torch

_active: FrameCache | None = None


class FrameCache:
    """Context manager: `with FrameCache(max_gb=8): ...` caches decoded frames inside the block."""

    def __init__(self, max_gb: float):
        if isinstance(max_gb, bool) or not isinstance(max_gb, int | float) or not max_gb > 0:
            raise ValueError(
                f"frame cache size max_gb={max_gb!r} is not allowed; allowed: a number > 0 (GiB)"
            )
        self.max_bytes = int(max_gb * 2**30)
        self.bytes = self.hits = self.misses = 0
        self._frames: dict[tuple, dict[str, torch.Tensor]] = {}

    def __enter__(self) -> FrameCache:
        global _active
        if _active is not None:
            raise RuntimeError("a FrameCache is already active")
        _install()
        _active = self
        return self

    def __exit__(self, *exc) -> None:
        global _active
        _active = None

    def query(self, reader, query_timestamps: dict[str, list[float]], ep_idx: int, decode) -> dict:
        key = (str(reader.root), ep_idx, tuple((k, tuple(ts)) for k, ts in query_timestamps.items()))
        frames = self._frames.get(key)
        if frames is not None:
            self.hits += 1
            return dict(frames)
        self.misses += 1
        frames = decode(reader, query_timestamps, ep_idx)
        size = sum(v.numel() * v.element_size() for v in frames.values())
        if self.bytes + size <= self.max_bytes:
            self._frames[key] = dict(frames)
            self.bytes += size
        return frames


@functools.cache
def _install() -> None:
    """Routes LeRobot's video query through the active cache (a no-op while none is active)."""
    from lerobot.datasets.dataset_reader import DatasetReader

    decode = DatasetReader._query_videos

    @functools.wraps(decode)
    def query_videos(self, query_timestamps, ep_idx):
        if _active is None:
            return decode(self, query_timestamps, ep_idx)
        return _active.query(self, query_timestamps, ep_idx, decode)

    DatasetReader._query_videos = query_videos
