"""Geometry identities: poses, intrinsics scaling, back-projection and the warp (against kornia too)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from kornia.geometry.depth import warp_frame_depth

from endoflow.geometry.camera import backproject, intrinsics_inverse, pixel_grid, project, scale_intrinsics
from endoflow.geometry.pose import (
    axis_angle_to_matrix,
    invert_pose,
    matrix_to_pose_vec,
    mean_step,
    matrix_to_quaternion_xyzw,
    opencv_to_unity,
    pose_vec_to_matrix,
    quaternion_xyzw_to_matrix,
    relative_pose,
    step_root,
    unity_to_opencv,
)
from endoflow.geometry.warp import warp_frame
from tests.samples import SIMCOL_SAMPLE

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def random_poses(*shape: int, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    vec = torch.randn(*shape, 6, generator=generator, dtype=torch.float64)
    vec[..., :3] *= 0.8
    return pose_vec_to_matrix(vec)


def camera_K(batch: int, height: int, width: int, focal: float = 20.0) -> torch.Tensor:
    K = torch.tensor([[focal, 0, (width - 1) / 2], [0, focal * 1.1, (height - 1) / 2], [0, 0, 1]])
    return K.expand(batch, 3, 3).clone()


# ---------------------------------------------------------------------------------------------- poses
def test_quarter_turn_about_z_maps_x_to_y() -> None:
    rotation = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2]))
    assert torch.allclose(rotation @ torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]), atol=1e-6)


def test_rotations_are_proper_for_any_leading_shape() -> None:
    rotation = axis_angle_to_matrix(torch.randn(2, 3, 3, dtype=torch.float64))
    assert rotation.shape == (2, 3, 3, 3)
    identity = torch.eye(3, dtype=torch.float64).expand_as(rotation)
    assert torch.allclose(rotation @ rotation.transpose(-1, -2), identity, atol=1e-12)
    assert torch.allclose(torch.linalg.det(rotation), torch.ones(2, 3, dtype=torch.float64))


def test_pose_vector_round_trip() -> None:
    # seeded: about 1 draw in 100 of an unseeded one has an angle above pi, where the round trip cannot hold
    vec = torch.randn(7, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    vec[:, :3] *= 0.8  # angles below pi, where the axis-angle vector is unique
    T = pose_vec_to_matrix(vec)
    assert T.shape == (7, 4, 4)
    assert torch.equal(T[:, 3], torch.tensor([0.0, 0, 0, 1], dtype=torch.float64).expand(7, 4))
    assert torch.equal(T[:, :3, 3], vec[:, 3:])
    assert torch.allclose(matrix_to_pose_vec(T), vec, atol=1e-9)


def test_zero_pose_vector_is_the_identity_and_gradients_flow() -> None:
    vec = torch.zeros(2, 6, requires_grad=True)
    T = pose_vec_to_matrix(vec)
    assert torch.equal(T.detach(), torch.eye(4).expand(2, 4, 4))
    (T * torch.randn(2, 4, 4)).sum().backward()
    assert torch.isfinite(vec.grad).all() and vec.grad.abs().sum() > 0


def test_rigid_inverse_matches_matrix_inverse_torch_and_numpy() -> None:
    T = random_poses(5)
    assert torch.allclose(invert_pose(T), torch.linalg.inv(T), atol=1e-12)
    assert torch.allclose(invert_pose(T) @ T, torch.eye(4, dtype=torch.float64).expand(5, 4, 4), atol=1e-12)
    T_np = T.numpy()
    assert isinstance(invert_pose(T_np), np.ndarray)
    assert np.allclose(invert_pose(T_np), np.linalg.inv(T_np), atol=1e-12)


def test_relative_pose_maps_target_points_into_source_frame() -> None:
    T_world_s, T_world_t = random_poses(2, seed=1).unbind(0)
    T_s_t = relative_pose(T_world_s, T_world_t)
    point_t = torch.tensor([0.3, -0.2, 2.0, 1.0], dtype=torch.float64)
    # The same world point, expressed in s's frame directly and through T_s_t.
    assert torch.allclose(T_s_t @ point_t, invert_pose(T_world_s) @ (T_world_t @ point_t), atol=1e-12)
    assert torch.allclose(T_world_s @ T_s_t, T_world_t, atol=1e-12)


def test_relative_poses_compose_numpy() -> None:
    a, b, c = random_poses(3, seed=2).numpy()
    assert np.allclose(relative_pose(a, b) @ relative_pose(b, c), relative_pose(a, c), atol=1e-12)
    assert np.allclose(relative_pose(a, a), np.eye(4), atol=1e-12)


def test_quaternion_of_quarter_turn_about_z() -> None:
    half = math.sqrt(0.5)
    R = quaternion_xyzw_to_matrix(np.array([0.0, 0.0, half, half]))
    assert np.allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


def test_quaternions_sign_flip_invariant_and_round_trip() -> None:
    q = np.random.default_rng(0).normal(size=(50, 4))
    R = quaternion_xyzw_to_matrix(q)
    assert np.allclose(quaternion_xyzw_to_matrix(-q), R)
    assert np.allclose(quaternion_xyzw_to_matrix(3 * q), R)  # normalised first
    back = matrix_to_quaternion_xyzw(R)
    assert np.all(back[:, 3] >= 0)
    assert np.allclose(np.abs(np.sum(back * q / np.linalg.norm(q, axis=1, keepdims=True), axis=1)), 1)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_half_turns_round_trip(axis: int) -> None:
    # qw = 0: the branches of the matrix-to-quaternion conversion that divide by qx, qy or qz.
    R = np.diag([-1.0, -1.0, -1.0])
    R[axis, axis] = 1
    assert np.allclose(quaternion_xyzw_to_matrix(matrix_to_quaternion_xyzw(R)), R, atol=1e-12)


def test_unity_conversion_is_an_involution_giving_proper_rotations() -> None:
    M = np.tile(np.eye(4), (4, 1, 1))
    M[:, :3, :3] = quaternion_xyzw_to_matrix(np.random.default_rng(1).normal(size=(4, 4)))
    M[:, :3, 3] = [1.0, 2.0, 3.0]
    P = unity_to_opencv(M)
    assert np.allclose(np.linalg.det(P[:, :3, :3]), 1)
    assert np.allclose(P[:, :3, 3], [1.0, -2.0, 3.0])  # y flips, x and z stay
    assert np.allclose(opencv_to_unity(P), M)


@pytest.mark.skipif(not SIMCOL_SAMPLE.is_dir(), reason=f"real SimCol3D sample not found at {SIMCOL_SAMPLE}")
def test_official_conversion_of_real_simcol_poses() -> None:
    scene = SIMCOL_SAMPLE / "SyntheticColon_I"
    positions = np.loadtxt(scene / "SavedPosition_S1.txt")
    quaternions = np.loadtxt(scene / "SavedRotationQuaternion_S1.txt")
    M = np.tile(np.eye(4), (len(positions), 1, 1))
    M[:, :3, :3] = quaternion_xyzw_to_matrix(quaternions)
    M[:, :3, 3] = positions
    expected = np.loadtxt(SIMCOL_SAMPLE / "S1_first10_converted_kitti3x4.txt").reshape(-1, 3, 4)
    assert np.allclose(unity_to_opencv(M)[:, :3], expected, atol=1e-5)


# --------------------------------------------------------------------------------------------- camera
def test_scale_intrinsics_numpy_and_torch_agree() -> None:
    K = np.array([[100.0, 0, 63.5], [0, 90, 47.5], [0, 0, 1]])
    scaled = scale_intrinsics(K, 0.5, 0.25)
    assert np.allclose(scaled, [[50, 0, 31.5], [0, 22.5, 11.5], [0, 0, 1]])
    assert torch.allclose(scale_intrinsics(torch.from_numpy(K)[None], 0.5, 0.25)[0], torch.from_numpy(scaled))
    assert K[0, 0] == 100  # input untouched


@pytest.mark.parametrize(
    "scale, interpolation", [(0.5, cv2.INTER_AREA), (0.5, cv2.INTER_LINEAR), (2.0, cv2.INTER_LINEAR)]
)
def test_scaled_intrinsics_follow_cv2_resize(scale: float, interpolation: int) -> None:
    # An image whose value is its own column (row) coordinate, resized: sampling the resized image where
    # the scaled K projects a 3D point must give the column (row) where the original K projects it.
    height, width = 40, 60
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    K = np.array([[50.0, 0, 29.0], [0, 45, 21.0], [0, 0, 1]])
    K_scaled = scale_intrinsics(K, scale, scale)
    size = (round(width * scale), round(height * scale))
    for image, axis in ((u, 0), (v, 1)):
        resized = cv2.resize(image, size, interpolation=interpolation)
        point = np.array([0.1, -0.05, 1.0])
        original = (K @ point)[:2]
        moved = (K_scaled @ point)[:2]
        x0, y0 = np.floor(moved).astype(int)
        fx, fy = moved - [x0, y0]
        patch = resized[y0 : y0 + 2, x0 : x0 + 2]
        sampled = (patch * [[(1 - fx) * (1 - fy), fx * (1 - fy)], [(1 - fx) * fy, fx * fy]]).sum()
        assert sampled == pytest.approx(original[axis], abs=1e-3)


def test_closed_form_intrinsics_inverse() -> None:
    K = torch.tensor([[[100.0, 0.5, 63.5], [0, 90, 47.5], [0, 0, 1]], [[20.0, 0, 9.5], [0, 22, 7.5], [0, 0, 1]]])
    assert torch.allclose(intrinsics_inverse(K.double()), torch.linalg.inv(K.double()), atol=1e-15)


def test_backproject_then_project_returns_pixels_and_depth() -> None:
    height, width = 6, 9
    depth = 1 + torch.rand(2, 1, height, width, dtype=torch.float64)
    K = camera_K(2, height, width).double()
    points = backproject(depth, torch.linalg.inv(K))
    assert points.shape == (2, 3, height * width)
    assert torch.allclose(points[:, 2], depth.reshape(2, -1))
    grid = pixel_grid(height, width, torch.device("cpu"), torch.float64)[:2]
    assert torch.allclose(project(points, K), grid.expand(2, 2, -1), atol=1e-10)


def test_a_pixel_grid_first_made_in_inference_mode_serves_autograd_later() -> None:
    # evaluation tracks under inference mode; a model fitted afterwards in the same process warps with the same grid
    with torch.inference_mode():
        backproject(torch.ones(1, 1, 7, 5), torch.eye(3)[None])
    depth = torch.ones(1, 1, 7, 5, requires_grad=True)
    backproject(depth, torch.eye(3)[None]).sum().backward()
    assert not pixel_grid(7, 5, torch.device("cpu"), torch.float32).is_inference()
    assert depth.grad is not None


def test_shape_errors_name_the_argument() -> None:
    with pytest.raises(ValueError, match="depth"):
        backproject(torch.ones(1, 2, 4, 4), torch.eye(3)[None])
    with pytest.raises(ValueError, match="T_src_tgt"):
        warp_frame(torch.ones(2, 3, 4, 4), torch.ones(2, 1, 4, 4), torch.eye(4)[None], camera_K(2, 4, 4))


# ----------------------------------------------------------------------------------------------- warp
@pytest.mark.parametrize("device", DEVICES)
def test_identity_pose_returns_the_image(device: str) -> None:
    image = torch.rand(2, 3, 12, 16, device=device)
    depth = 0.5 + torch.rand(2, 1, 12, 16, device=device)
    T = torch.eye(4, device=device).expand(2, 4, 4)
    warped, valid = warp_frame(image, depth, T, camera_K(2, 12, 16).to(device))
    assert valid.dtype == torch.bool and valid.shape == (2, 1, 12, 16) and valid.all()
    assert torch.allclose(warped, image, atol=1e-5)


@pytest.mark.parametrize("axis", [0, 1])
def test_translated_fronto_parallel_plane_shifts_by_focal_times_baseline_over_depth(axis: int) -> None:
    height, width, focal, depth_value, shift = 10, 14, 10.0, 2.0, 3
    K = torch.tensor([[[focal, 0, 6.5], [0, focal, 4.5], [0, 0, 1]]])
    T_src_tgt = torch.eye(4)[None].clone()
    T_src_tgt[0, axis, 3] = shift * depth_value / focal  # target points move by this in the source frame
    image = torch.rand(1, 2, height, width)
    warped, valid = warp_frame(image, torch.full((1, 1, height, width), depth_value), T_src_tgt, K)
    if axis == 0:
        assert torch.allclose(warped[..., :, : width - shift], image[..., :, shift:], atol=1e-5)
        assert valid[..., :, : width - shift].all() and not valid[..., :, width - shift :].any()
    else:
        assert torch.allclose(warped[..., : height - shift, :], image[..., shift:, :], atol=1e-5)
        assert valid[..., : height - shift, :].all() and not valid[..., height - shift :, :].any()


def test_points_behind_the_source_camera_are_invalid() -> None:
    T_src_tgt = torch.eye(4)[None].clone()
    T_src_tgt[0, 2, 3] = -5.0  # source camera 5 units in front of a plane at depth 1
    _, valid = warp_frame(torch.rand(1, 3, 8, 8), torch.ones(1, 1, 8, 8), T_src_tgt, camera_K(1, 8, 8))
    assert not valid.any()


@pytest.mark.parametrize("device", DEVICES)
def test_agrees_with_kornia_warp_frame_depth(device: str) -> None:
    batch, height, width = 3, 24, 32
    generator = torch.Generator().manual_seed(3)
    image = torch.rand(batch, 3, height, width, generator=generator).to(device)
    depth = (1 + 3 * torch.rand(batch, 1, height, width, generator=generator)).to(device)
    T = pose_vec_to_matrix(0.05 * torch.randn(batch, 6, generator=generator)).to(device)
    K = camera_K(batch, height, width).to(device)
    warped, valid = warp_frame(image, depth, T, K)
    reference = warp_frame_depth(image, depth, T, K)
    assert torch.allclose(warped, reference, atol=1e-4)
    assert 0.3 < valid.float().mean() < 1  # the comparison covers both inside and outside samples


def test_batch_size_independent() -> None:
    generator = torch.Generator().manual_seed(4)
    image = torch.rand(4, 3, 16, 20, generator=generator)
    depth = 1 + torch.rand(4, 1, 16, 20, generator=generator)
    T = pose_vec_to_matrix(0.1 * torch.randn(4, 6, generator=generator))
    K = camera_K(4, 16, 20)
    warped, valid = warp_frame(image, depth, T, K)
    for i in range(4):
        single, single_valid = warp_frame(image[i : i + 1], depth[i : i + 1], T[i : i + 1], K[i : i + 1])
        assert torch.allclose(single, warped[i : i + 1], atol=1e-6)
        assert torch.equal(single_valid, valid[i : i + 1])


def test_gradients_reach_depth_and_pose_vector() -> None:
    image = F.avg_pool2d(torch.rand(2, 3, 20, 20), 3, 1, 1)  # smooth, so that sampling has a gradient
    depth = (1 + torch.rand(2, 1, 20, 20)).requires_grad_()
    vec = (0.02 * torch.randn(2, 6)).requires_grad_()
    warped, _ = warp_frame(image, depth, pose_vec_to_matrix(vec), camera_K(2, 20, 20))
    (warped - image).square().mean().backward()
    assert depth.grad.abs().sum() > 0 and torch.isfinite(depth.grad).all()
    assert (vec.grad.abs() > 0).all() and torch.isfinite(vec.grad).all()


def test_low_precision_keeps_geometry_in_float32() -> None:
    generator = torch.Generator().manual_seed(5)
    image = torch.rand(2, 3, 32, 32, generator=generator)
    depth = 1 + torch.rand(2, 1, 32, 32, generator=generator)
    T = pose_vec_to_matrix(0.05 * torch.randn(2, 6, generator=generator))
    K = camera_K(2, 32, 32)
    reference, reference_valid = warp_frame(image, depth, T, K)
    warped_bf16, _ = warp_frame(image.bfloat16(), depth.bfloat16(), T, K)
    assert warped_bf16.dtype == torch.bfloat16
    assert (warped_bf16.float() - reference).abs().mean() < 0.02  # bf16 input rounding only
    with torch.autocast("cpu", dtype=torch.bfloat16):
        warped_autocast, valid_autocast = warp_frame(image, depth, T, K)
    assert torch.allclose(warped_autocast.float(), reference, atol=1e-5)
    assert torch.equal(valid_autocast, reference_valid)


def test_chain_step_is_the_inverse_step_composed_and_stays_rigid():
    from endoflow.geometry.pose import chain_step, nearest_rotation

    rng = np.random.default_rng(4)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    step = np.eye(4)
    step[:3, :3], step[:3, 3] = q * np.sign(np.linalg.det(q)), rng.normal(size=3)
    start = np.eye(4)
    start[:3, 3] = (1.0, 2.0, 3.0)
    np.testing.assert_allclose(chain_step(start, step), start @ np.linalg.inv(step), atol=1e-12)
    noisy = step[:3, :3] + 1e-4 * rng.standard_normal((3, 3))
    rotation = nearest_rotation(noisy)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0) and np.abs(rotation - step[:3, :3]).max() < 1e-3


def test_orthonormality_error_is_zero_for_rotations_and_mirrors_and_grows_with_a_stretch():
    from endoflow.geometry.pose import orthonormality_error

    rotation = axis_angle_to_matrix(torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)).numpy()
    mirror = np.diag([-1.0, 1.0, 1.0])
    stretched = np.diag([1.01, 1.0, 1.0])
    errors = orthonormality_error(np.stack([rotation, mirror, stretched]))
    assert errors.shape == (3,) and errors[0] < 1e-15 and errors[1] == 0
    assert errors[2] == pytest.approx(1.01 ** 2 - 1)
    assert orthonormality_error(stretched).shape == ()  # one matrix: one number


def test_nearest_rigid_keeps_a_rigid_pose_and_makes_a_shrunken_rotation_rigid_again():
    from endoflow.geometry.pose import nearest_rigid

    T = pose_vec_to_matrix(torch.tensor([0.3, -0.2, 0.1, 1.0, 2.0, 3.0], dtype=torch.float64))
    torch.testing.assert_close(nearest_rigid(T), T, rtol=0, atol=1e-12)
    shrunk = T.clone()
    shrunk[:3, :3] *= 0.9
    shrunk[3, 0] = 1e-3
    torch.testing.assert_close(nearest_rigid(shrunk), T, rtol=0, atol=1e-12)


@pytest.mark.parametrize("count", [1, 2, 3, 4])
def test_a_step_repeated_count_times_has_that_step_as_its_root(count):
    rng = np.random.default_rng(count)
    vectors = np.concatenate([rng.uniform(-0.4, 0.4, (5, 3)), rng.normal(size=(5, 3))], axis=1)
    steps = pose_vec_to_matrix(torch.from_numpy(vectors)).numpy()
    spans = np.stack([np.linalg.matrix_power(step, count) for step in steps])
    np.testing.assert_allclose(step_root(spans, count), steps, atol=1e-12)


def test_a_step_root_needs_a_positive_count():
    with pytest.raises(ValueError, match="count must be positive"):
        step_root(np.eye(4)[None], 0)


def test_the_mean_step_of_equal_steps_is_that_step_and_of_no_steps_the_identity():
    step = pose_vec_to_matrix(torch.tensor([0.01, -0.02, 0.005, 0.1, 0.0, 0.13], dtype=torch.float64)).numpy()
    np.testing.assert_allclose(mean_step(np.stack([step] * 5)), step, atol=1e-12)
    np.testing.assert_array_equal(mean_step(np.zeros((0, 4, 4))), np.eye(4))
    # a turn and the same turn back average to no motion (the mean is over axis-angle and translation vectors)
    turn = pose_vec_to_matrix(torch.tensor([0.01, -0.02, 0.005, 0.0, 0.0, 0.0], dtype=torch.float64)).numpy()
    np.testing.assert_allclose(mean_step(np.stack([turn, np.linalg.inv(turn)])), np.eye(4), atol=1e-12)
