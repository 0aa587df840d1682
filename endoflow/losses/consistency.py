"""Depth consistency between neighbouring frames (SC-SfMLearner's geometry consistency: Bian et al., "Unsupervised
scale-consistent depth and ego-motion learning from monocular video", NeurIPS 2019).

A target pixel with depth ``d`` back-projects to a point; moved into the source camera by ``T_src_tgt`` it has
source z-depth ``z`` and lands at source pixel ``p``. The source frame's own predicted depth there, ``D_src(p)``
(bilinear), should be ``z``. The normalised difference ``|D_src(p) - z| / (D_src(p) + z)`` (in [0, 1), blind to a
common scale) is averaged over pixels that land inside the source image in front of its camera. Both depths come
from one network and the move from the pose network, so agreement over neighbouring frames ties every frame's depth
to one scale, and the path to the same scale (docs/method.md).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from endoflow.geometry.warp import project_target_pixels, sampling_grid
from endoflow.shapes import check_shape

# keeps the ratio finite where both depths vanish (depth is at least model.min_depth, 0.1 cm, in training)
_EPS = 1e-7


def depth_inconsistency(
    depth_tgt: torch.Tensor, depth_src: torch.Tensor, T_src_tgt: torch.Tensor, K: torch.Tensor,
    in_view: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel normalised depth difference of the target's points seen from the source.

    Args:
        depth_tgt, depth_src: ``[B, 1, H, W]`` z-depth of the target and the source frame (one unit).
        T_src_tgt: ``[B, 4, 4]``, maps target-camera points into the source camera.
        K: ``[B, 3, 3]`` pixel intrinsics of both frames.
        in_view: ``[B, 1, H, W]`` bool, the field of view shared by both frames (None: everywhere): a pixel counts
            where it is in view and lands in view (the four pixels around its sample all are).

    Returns:
        ``difference [B, 1, H, W]`` in [0, 1) (0 where invalid) and ``valid [B, 1, H, W]`` bool: the point lies in
        front of the source camera and projects inside the source image (and its field of view).
    """
    sizes = check_shape("depth_tgt", depth_tgt, "B,1,H,W")
    check_shape("depth_src", depth_src, "B,1,H,W", **sizes)
    check_shape("T_src_tgt", T_src_tgt, "B,4,4", **sizes)
    check_shape("K", K, "B,3,3", **sizes)
    batch, _, height, width = depth_tgt.shape
    pixels, z = project_target_pixels(depth_tgt, T_src_tgt, K)
    u, v = pixels[:, 0], pixels[:, 1]
    valid = (z > 0) & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
    grid = sampling_grid(u, v, height, width)
    seen = F.grid_sample(depth_src.to(grid.dtype), grid.reshape(batch, height, width, 2), mode="bilinear",
                         padding_mode="border", align_corners=True).reshape(batch, height * width)
    if in_view is not None:
        check_shape("in_view", in_view, "B,1,H,W", **sizes)
        lands_in_view = F.grid_sample(in_view.to(grid.dtype), grid.reshape(batch, height, width, 2), mode="bilinear",
                                      padding_mode="zeros", align_corners=True).reshape(batch, height * width)
        valid = valid & in_view.reshape(batch, height * width) & (lands_in_view > 0.999)
    difference = (seen - z).abs() / (seen + z.clamp(min=0) + _EPS)
    difference = torch.where(valid, difference, torch.zeros_like(difference))
    return difference.reshape(batch, 1, height, width), valid.reshape(batch, 1, height, width)


def geometry_consistency(
    depth_tgt: torch.Tensor, depth_srcs: list[torch.Tensor], T_src_tgts: list[torch.Tensor], K: torch.Tensor,
    in_view: torch.Tensor | None = None,
) -> torch.Tensor:
    """Scalar: :func:`depth_inconsistency` averaged over the valid pixels of every source (0 where none is valid);
    ``in_view`` as there."""
    if len(depth_srcs) != len(T_src_tgts) or not depth_srcs:
        raise ValueError(f"expected one pose per source depth, got {len(depth_srcs)} depths and "
                         f"{len(T_src_tgts)} poses")
    total, count = depth_tgt.new_zeros(()), depth_tgt.new_zeros(())
    for depth_src, T in zip(depth_srcs, T_src_tgts):
        difference, valid = depth_inconsistency(depth_tgt, depth_src, T, K, in_view)
        total = total + difference.sum()
        count = count + valid.sum()
    return total / count.clamp(min=1)
