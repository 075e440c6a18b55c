"""The overlaps of the paper's eq. (1), shared by every policy that regularizes its attention:
<A, M_phi> (attention on the relevant entity) and <A, M_d> (attention on the distractors), for an
attention map over a token grid and pixel masks of the camera the grid covers."""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor


def pooled_mask(mask: Tensor, grid: tuple[int, int]) -> Tensor:
    """(B, H, W) bool mask -> (B, h, w) pixel coverage per token, scaled so the most covered token is 1.
    An empty mask stays all zeros."""
    coverage = F.adaptive_avg_pool2d(mask.float().unsqueeze(1), grid).squeeze(1)
    return coverage / coverage.amax(dim=(1, 2), keepdim=True).clamp_min(1e-6)


def overlaps(attention: Tensor, relevant: Tensor, distractors: Tensor) -> tuple[Tensor, Tensor]:
    """(<A, M_phi>, <A, M_d>) per sample for attention (B, h, w) summing to at most 1 over the grid and pixel
    masks (B, H, W) of the same camera."""
    grid = tuple(attention.shape[-2:])
    return (
        (attention * pooled_mask(relevant, grid)).sum(dim=(1, 2)),
        (attention * pooled_mask(distractors, grid)).sum(dim=(1, 2)),
    )
