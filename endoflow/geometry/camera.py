"""Pinhole camera: intrinsics scaling, back-projection and projection (OpenCV convention).

Pixel coordinates put pixel centres at integers: the ray through pixel ``(u, v)`` (column, row) is
``K^-1 [u, v, 1]^T`` and the top-left pixel's centre is ``(0, 0)``. Depth is z-depth (distance along the
optical axis), so a pixel with depth ``d`` back-projects to ``d * K^-1 [u, v, 1]^T``.
"""

from __future__ import annotations

from functools import lru_cache
from typing import TypeVar

import numpy as np
import torch

from endoflow.shapes import check_shape

ArrayOrTensor = TypeVar("ArrayOrTensor", np.ndarray, torch.Tensor)
# the least depth a projection divides by, so points on or behind the camera plane stay finite
PROJECTION_EPS = 1e-6


def scale_intrinsics(K: ArrayOrTensor, sx: float, sy: float) -> ArrayOrTensor:
    """K ``[..., 3, 3]`` for an image resized by ``sx`` horizontally and ``sy`` vertically.

    Resizing whole images (``cv2.resize``, ``F.interpolate(align_corners=False)``) maps pixel-area edges to
    edges, so with pixel centres at integers a point moves as ``u' = (u + 0.5) * sx - 0.5``. Hence
    ``fx' = fx * sx`` and ``cx' = (cx + 0.5) * sx - 0.5`` (the same with ``sy`` for ``fy``, ``cy``).
    Cropping is a separate shift of ``cx``, ``cy``. Works on numpy arrays and tensors, batched.
    """
    check_shape("K", K, "...,3,3")
    scaled = K.clone() if isinstance(K, torch.Tensor) else np.array(K, dtype=np.float64)
    scaled[..., 0, 0] = K[..., 0, 0] * sx
    scaled[..., 0, 1] = K[..., 0, 1] * sx
    scaled[..., 0, 2] = (K[..., 0, 2] + 0.5) * sx - 0.5
    scaled[..., 1, 1] = K[..., 1, 1] * sy
    scaled[..., 1, 2] = (K[..., 1, 2] + 0.5) * sy - 0.5
    return scaled


def intrinsics_inverse(K: torch.Tensor) -> torch.Tensor:
    """``K^-1`` ``[..., 3, 3]`` of pinhole intrinsics ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in closed form.

    Cheaper than a general inverse, and on GPU it needs no linear-algebra library call or sync.
    """
    check_shape("K", K, "...,3,3")
    fx, skew, cx = K[..., 0, 0], K[..., 0, 1], K[..., 0, 2]
    fy, cy = K[..., 1, 1], K[..., 1, 2]
    zero, one = torch.zeros_like(fx), torch.ones_like(fx)
    rows = [
        [1 / fx, -skew / (fx * fy), (skew * cy - cx * fy) / (fx * fy)],
        [zero, 1 / fy, -cy / fy],
        [zero, zero, one],
    ]
    return torch.stack([torch.stack(row, dim=-1) for row in rows], dim=-2)


@lru_cache(maxsize=32)
def pixel_grid(height: int, width: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """Homogeneous pixel coordinates ``[3, H*W]`` (rows ``u``, ``v``, ``1``), row-major over the image.

    Cached per (H, W, device, dtype): the result is shared, never modify it in place. Made outside inference mode
    whatever the caller's: a grid first asked for under ``torch.inference_mode`` (evaluation's tracker) would
    otherwise be an inference tensor, which training, fitting a model with the same grid, cannot use.
    """
    with torch.inference_mode(False):
        v, u = torch.meshgrid(
            torch.arange(height, device=device, dtype=dtype),
            torch.arange(width, device=device, dtype=dtype),
            indexing="ij",
        )
        return torch.stack([u.reshape(-1), v.reshape(-1), torch.ones_like(u).reshape(-1)])


def backproject(depth: torch.Tensor, K_inv: torch.Tensor) -> torch.Tensor:
    """3D points ``[B, 3, H*W]`` in the camera frame from z-depth ``[B, 1, H, W]`` and ``K^-1`` ``[B, 3, 3]``."""
    sizes = check_shape("depth", depth, "B,1,H,W")
    check_shape("K_inv", K_inv, "B,3,3", B=sizes["B"])
    height, width = sizes["H"], sizes["W"]
    rays = K_inv @ pixel_grid(height, width, depth.device, depth.dtype)
    return rays * depth.reshape(depth.shape[0], 1, -1)


def project(points: torch.Tensor, K: torch.Tensor, eps: float = PROJECTION_EPS) -> torch.Tensor:
    """Pixel coordinates ``[B, 2, N]`` (u, v) of camera-frame points ``[B, 3, N]`` through K ``[B, 3, 3]``.

    ``z`` is clamped to at least ``eps`` so points on or behind the camera plane stay finite; callers that
    need them masked test ``points[:, 2] > 0`` themselves.
    """
    sizes = check_shape("points", points, "B,3,N")
    check_shape("K", K, "B,3,3", B=sizes["B"])
    homogeneous = K @ points
    return homogeneous[:, :2] / homogeneous[:, 2:3].clamp(min=eps)
