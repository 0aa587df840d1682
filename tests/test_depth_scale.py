"""The factor that brings a frame's depth to its keyframe's (endoflow.geometry.depth_scale), on scenes whose answer
is known by hand."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from endoflow.geometry.depth_scale import MIN_POINTS, depth_scale_to_keyframe
from endoflow.geometry.pose import pose_vec_to_matrix

SIZE = 32
K = torch.tensor([[30.0, 0.0, 15.5], [0.0, 30.0, 15.5], [0.0, 0.0, 1.0]], dtype=torch.float64)


def plane(depth: float) -> torch.Tensor:
    """``[1, H, W]`` a wall facing the camera at ``depth``."""
    return torch.full((1, SIZE, SIZE), depth, dtype=torch.float32)


def forward(distance: float) -> torch.Tensor:
    """``T_frame_key`` of a camera that moved ``distance`` along its optical axis."""
    T = torch.eye(4, dtype=torch.float64)
    T[2, 3] = -distance
    return T


def test_the_same_depth_from_the_same_place_needs_no_factor():
    assert depth_scale_to_keyframe(plane(5.0), plane(5.0), K, torch.eye(4, dtype=torch.float64)) == pytest.approx(1.0)


@pytest.mark.parametrize("factor", [0.5, 1.0, 1.5])
def test_a_frame_that_moved_towards_a_wall_and_predicts_it_off_scale_gets_the_factor_that_undoes_it(factor: float):
    # the wall at 5 from the keyframe is at 4 from the frame, which predicts 4 / factor
    assert depth_scale_to_keyframe(plane(5.0), plane(4.0 / factor), K, forward(1.0)) == pytest.approx(factor)


def test_a_turned_camera_is_answered_through_its_pose_not_its_pixels():
    """The keyframe sees a slanted floor; the frame, turned and moved, sees it at other pixels and depths: its own
    depth, computed exactly from the same floor and divided by 1.3, gets 1.3 back."""
    T_frame_key = pose_vec_to_matrix(torch.tensor([0.02, -0.03, 0.01, 0.1, -0.05, 0.3], dtype=torch.float64))
    normal, offset = torch.tensor([0.0, -0.3, -1.0], dtype=torch.float64), -6.0  # n . X = offset, X in the keyframe
    v, u = torch.meshgrid(torch.arange(SIZE, dtype=torch.float64), torch.arange(SIZE, dtype=torch.float64),
                          indexing="ij")

    def depth_seen(T_cam_key: torch.Tensor) -> torch.Tensor:
        # the ray through each pixel of a camera at T_cam_key meets the plane at z = offset' / (n' . ray)
        R, t = T_cam_key[:3, :3], T_cam_key[:3, 3]
        normal_cam = R @ normal
        offset_cam = offset + float(normal_cam @ t)
        rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)])
        return (offset_cam / torch.einsum("c,chw->hw", normal_cam, rays))[None].float()

    key, frame = depth_seen(torch.eye(4, dtype=torch.float64)), depth_seen(T_frame_key)
    assert bool((key > 0).all() and (frame > 0).all())
    # the nearest pixel's depth stands for the point's: on a slanted floor that costs a little
    assert depth_scale_to_keyframe(key, frame / 1.3, K, T_frame_key) == pytest.approx(1.3, rel=2e-3)


def test_unknown_depth_on_either_side_does_not_count():
    frame = plane(2.0)
    frame[:, :, : 3 * SIZE // 4] = 0  # three quarters of the frame unknown: counted, they would set the median
    key = plane(4.0)
    key[:, : SIZE // 2] = 0  # the keyframe's top half unknown
    assert depth_scale_to_keyframe(key, frame, K, torch.eye(4, dtype=torch.float64)) == pytest.approx(2.0)
    frame[:] = 0
    assert depth_scale_to_keyframe(key, frame, K, torch.eye(4, dtype=torch.float64)) is None


def test_too_few_points_landing_in_front_of_the_frame_give_no_factor():
    # moved past the wall: every keyframe point lies behind the frame's camera
    assert depth_scale_to_keyframe(plane(5.0), plane(1.0), K, forward(6.0)) is None
    few = torch.zeros(1, SIZE, SIZE)
    few.view(-1)[: MIN_POINTS - 1] = 5.0
    assert depth_scale_to_keyframe(few, plane(5.0), K, torch.eye(4, dtype=torch.float64)) is None
    few.view(-1)[: MIN_POINTS] = 5.0
    assert depth_scale_to_keyframe(few, plane(5.0), K, torch.eye(4, dtype=torch.float64)) == pytest.approx(1.0)


def test_points_landing_outside_the_frame_do_not_count():
    # moved 2 sideways at 5 deep: the keyframe's points move 12 columns left, its first 12 columns out of the frame
    T = torch.eye(4, dtype=torch.float64)
    T[0, 3] = -2.0
    assert depth_scale_to_keyframe(plane(5.0), plane(2.5), K, T) == pytest.approx(2.0)
    # the frame's depth known only in its last 12 columns, where no point lands inside it (a negative column taken as
    # an index from the right would land there)
    right_only = plane(2.5)
    right_only[:, :, : SIZE - 12] = 0
    assert depth_scale_to_keyframe(plane(5.0), right_only, K, T) is None


def test_bad_shapes_are_refused_with_the_argument_named():
    with pytest.raises(ValueError, match="frame_depth"):
        depth_scale_to_keyframe(plane(5.0), torch.ones(1, SIZE, SIZE + 1), K, torch.eye(4, dtype=torch.float64))
    with pytest.raises(ValueError, match="T_frame_key"):
        depth_scale_to_keyframe(plane(5.0), plane(5.0), K, torch.eye(3, dtype=torch.float64))
    assert np.isfinite(depth_scale_to_keyframe(plane(5.0), plane(5.0), K.float(), torch.eye(4)))
