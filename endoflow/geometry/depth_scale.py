"""One scale for a sequence's depth: the factor that brings a frame's predicted depth to its keyframe's.

A depth network predicts each frame on its own, and its scale wanders with what the frame shows (on the real C3VD
sample the ground truth over the model's depth is 1.5 times as large in the last frames as in the first). A path
tracked against keyframe depths then takes each keyframe's local scale, and a map fused from such depths does not
close. Once a frame is aligned to its keyframe, the keyframe's points, moved into the frame's camera by the aligned
pose, say how far the frame's own pixels are: the median of their depth there over the frame's predicted depth where
they land is the frame's scale against the keyframe's (SC-SfMLearner's geometry consistency, Bian et al. 2019, as a
fit at test time rather than a loss). Chained from keyframe to keyframe, it puts every frame in the first frame's
scale. See docs/reconstruction.md, "The path refined against keyframes".
"""

from __future__ import annotations

from typing import Optional

import torch

from endoflow.geometry.camera import backproject, intrinsics_inverse, project
from endoflow.shapes import check_shape

# fewer keyframe points landing on the frame's known depth than this: no scale is fitted (the caller keeps its last)
MIN_POINTS = 64


def depth_scale_to_keyframe(key_depth: torch.Tensor, frame_depth: torch.Tensor, K: torch.Tensor,
                            T_frame_key: torch.Tensor, min_points: int = MIN_POINTS) -> Optional[float]:
    """The factor ``s`` for which ``s * frame_depth`` agrees with ``key_depth`` seen from the frame: the median,
    over keyframe pixels with depth that land in front of the frame's camera on a pixel with depth, of the point's
    z in the frame's camera over the frame's depth at the nearest pixel; None where fewer than ``min_points`` do.

    Args:
        key_depth, frame_depth: ``[1, H, W]`` z-depth (0: unknown) of the keyframe and the frame.
        K: ``[3, 3]`` pixel intrinsics of both.
        T_frame_key: ``[4, 4]`` maps keyframe-camera points into the frame's camera, in ``key_depth``'s unit.
    """
    sizes = check_shape("key_depth", key_depth, "1,H,W")
    check_shape("frame_depth", frame_depth, "1,H,W", **sizes)
    check_shape("K", K, "3,3")
    check_shape("T_frame_key", T_frame_key, "4,4")
    height, width = sizes["H"], sizes["W"]
    dtype = torch.float64  # a median of ratios: the points' arithmetic is cheap beside the alignment's
    K = K.to(key_depth.device, dtype)
    T = T_frame_key.to(key_depth.device, dtype)
    points = backproject(key_depth[None].to(dtype), intrinsics_inverse(K)[None])[0]
    points = points[:, key_depth.reshape(-1) > 0]
    moved = T[:3, :3] @ points + T[:3, 3:]
    pixels = project(moved[None], K[None])[0].round().long()
    u, v = pixels
    landed = (moved[2] > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    found = frame_depth[0].to(dtype)[v[landed], u[landed]]
    known = found > 0
    if int(known.sum()) < min_points:
        return None
    return float((moved[2][landed][known] / found[known]).median())
