"""``torch.autograd.gradcheck`` of every differentiable geometry and loss op, in float64 (as kornia tests each op).

Inputs are small and generic: random depths, poses and images put the warp's sample points off the pixel
grid (where bilinear sampling has kinks) and keep absolute values, minima and clamps away from their kinks.
"""

from __future__ import annotations

from typing import Callable

import pytest
import torch
from torch.autograd import gradcheck, gradgradcheck

from endoflow.config import LossConfig
from endoflow.geometry.camera import backproject, intrinsics_inverse, project, scale_intrinsics
from endoflow.geometry.pose import (
    axis_angle_to_matrix,
    invert_pose,
    matrix_to_axis_angle,
    matrix_to_pose_vec,
    pose_vec_to_matrix,
    relative_pose,
)
from endoflow.geometry.warp import project_target_pixels, warp_frame
from endoflow.losses.consistency import depth_inconsistency, geometry_consistency
from endoflow.losses.gan import critic_loss, generator_loss, gradient_penalty
from endoflow.losses.kl import kl_standard_normal
from endoflow.losses.photometric import photometric_error, reprojection_loss, ssim_map
from endoflow.losses.smoothness import edge_aware_smoothness
from endoflow.models.gemm_weight_grad import GemmWeightGradConv2d

HEIGHT, WIDTH = 6, 7


def generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def variable(tensor: torch.Tensor) -> torch.Tensor:
    """A float64 leaf that gradcheck differentiates with respect to."""
    return tensor.to(torch.float64).detach().requires_grad_(True)


def uniform(*shape: int, low: float = 0.0, high: float = 1.0, seed: int = 0) -> torch.Tensor:
    return variable(low + (high - low) * torch.rand(*shape, generator=generator(seed), dtype=torch.float64))


def intrinsics(batch: int = 1) -> torch.Tensor:
    """Pixel K for a HEIGHT x WIDTH image with a generic (non-integer) principal point and a little skew."""
    K = torch.tensor([[5.3, 0.1, 3.2], [0.0, 4.9, 2.7], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return variable(K.expand(batch, 3, 3).clone())


def small_pose_vec(batch: int = 1, seed: int = 1) -> torch.Tensor:
    """Pose vectors ``[B, 6]`` of a few degrees and a few percent of the depth: most pixels stay in view."""
    scale = torch.tensor([0.05, 0.05, 0.05, 0.1, 0.1, 0.1], dtype=torch.float64)
    return variable(scale * (2 * torch.rand(batch, 6, generator=generator(seed), dtype=torch.float64) - 1))


def rigid(batch: int = 1, seed: int = 1) -> torch.Tensor:
    return variable(pose_vec_to_matrix(small_pose_vec(batch, seed)))


def check(function: Callable[..., torch.Tensor], *inputs: torch.Tensor) -> None:
    assert gradcheck(function, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


# ------------------------------------------------------------------------------------------- camera
def test_scale_intrinsics_gradcheck():
    check(lambda K: scale_intrinsics(K, 0.5, 0.25), intrinsics(2))


def test_intrinsics_inverse_gradcheck():
    check(intrinsics_inverse, intrinsics(2))


def test_backproject_gradcheck():
    depth = uniform(2, 1, HEIGHT, WIDTH, low=1.0, high=3.0)
    check(backproject, depth, variable(intrinsics_inverse(intrinsics(2))))


def test_project_gradcheck():
    points = uniform(2, 3, 5, low=-1.0, high=1.0)
    with torch.no_grad():
        points[:, 2] += 3.0  # in front of the camera, away from the z clamp
    check(project, points, intrinsics(2))


# --------------------------------------------------------------------------------------------- pose
def test_axis_angle_to_matrix_gradcheck():
    check(axis_angle_to_matrix, uniform(3, 3, low=-1.0, high=1.0))


@pytest.mark.parametrize("angle", [0.0, 1e-4])
def test_axis_angle_to_matrix_gradcheck_at_and_near_the_identity(angle):
    """Where a fresh PoseNet starts: Rodrigues' formula divides by the angle, its small-angle branch must not."""
    axis = torch.tensor([[0.6, -0.8, 0.0], [0.0, 0.6, 0.8]], dtype=torch.float64)
    check(axis_angle_to_matrix, variable(angle * axis))


@pytest.mark.parametrize("scale", [1.0, 0.0])
def test_matrix_to_axis_angle_gradcheck(scale):
    # generic rotations (angles well inside (0, pi)), and the identity; gradcheck's perturbations leave the
    # rotation group, so this also checks the conversion is smooth around it
    axis_angle = scale * uniform(3, 3, low=-1.0, high=1.0, seed=2).detach()
    check(matrix_to_axis_angle, variable(axis_angle_to_matrix(axis_angle)))


def test_pose_vec_to_matrix_gradcheck():
    check(pose_vec_to_matrix, uniform(2, 6, low=-1.0, high=1.0))


def test_matrix_to_pose_vec_gradcheck():
    check(matrix_to_pose_vec, variable(pose_vec_to_matrix(uniform(2, 6, low=-1.0, high=1.0, seed=3))))


def test_invert_pose_gradcheck():
    check(invert_pose, rigid(2))


def test_relative_pose_gradcheck():
    check(relative_pose, rigid(2, seed=4), rigid(2, seed=5))


# --------------------------------------------------------------------------------------------- warp
def test_project_target_pixels_gradcheck():
    depth = uniform(1, 1, HEIGHT, WIDTH, low=1.0, high=3.0)
    check(project_target_pixels, depth, rigid(), intrinsics())


def test_warp_frame_gradcheck_in_image_depth_pose_and_intrinsics():
    image = uniform(1, 2, HEIGHT, WIDTH, seed=6)
    depth = uniform(1, 1, HEIGHT, WIDTH, low=1.0, high=3.0, seed=7)
    check(lambda *args: warp_frame(*args)[0], image, depth, rigid(seed=8), intrinsics())


def test_warp_from_a_pose_vector_gradcheck():
    """The training path of the pose gradient: vector -> matrix -> inverse (previous frame) -> warp."""
    image = uniform(1, 3, HEIGHT, WIDTH, seed=9).detach()
    depth = uniform(1, 1, HEIGHT, WIDTH, low=1.0, high=3.0, seed=10).detach()
    K = intrinsics().detach()

    def warped(vec: torch.Tensor) -> torch.Tensor:
        return warp_frame(image, depth, invert_pose(pose_vec_to_matrix(vec)), K)[0]

    check(warped, small_pose_vec(seed=11))


# ------------------------------------------------------------------------------------------- losses
def test_depth_inconsistency_gradcheck_in_both_depths_the_pose_and_intrinsics():
    depth_tgt = uniform(1, 1, HEIGHT, WIDTH, low=1.0, high=3.0, seed=30)
    depth_src = uniform(1, 1, HEIGHT, WIDTH, low=1.0, high=3.0, seed=31)
    check(lambda *args: depth_inconsistency(*args)[0], depth_tgt, depth_src, rigid(seed=32), intrinsics())


def test_geometry_consistency_gradcheck_over_two_sources():
    depths = [uniform(2, 1, HEIGHT, WIDTH, low=1.0, high=3.0, seed=s) for s in (33, 34, 35)]
    check(lambda tgt, a, b, Ta, Tb: geometry_consistency(tgt, [a, b], [Ta, Tb], intrinsics(2).detach()),
          *depths, rigid(2, seed=36), rigid(2, seed=37))


def test_ssim_gradcheck():
    check(ssim_map, uniform(1, 2, HEIGHT, WIDTH, seed=12), uniform(1, 2, HEIGHT, WIDTH, seed=13))


@pytest.mark.parametrize("kind", ["mse", "ssim_l1"])
def test_photometric_error_gradcheck(kind):
    check(lambda x, y: photometric_error(x, y, kind), uniform(1, 3, HEIGHT, WIDTH, seed=14),
          uniform(1, 3, HEIGHT, WIDTH, seed=15))


@pytest.mark.parametrize("automask", [False, True])
@pytest.mark.parametrize("min_reprojection", [False, True])
def test_reprojection_loss_gradcheck(automask, min_reprojection):
    cfg = LossConfig(automask=automask, min_reprojection=min_reprojection)
    target = uniform(1, 3, HEIGHT, WIDTH, seed=16).detach()
    sources = [uniform(1, 3, HEIGHT, WIDTH, seed=s).detach() for s in (17, 18)]

    def loss(*warped: torch.Tensor) -> torch.Tensor:
        torch.manual_seed(0)  # auto-masking's tie-breaking noise: the same draw on every evaluation
        return reprojection_loss(list(warped), target, sources, cfg)[0]

    check(loss, uniform(1, 3, HEIGHT, WIDTH, seed=19), uniform(1, 3, HEIGHT, WIDTH, seed=20))


@pytest.mark.parametrize("image_size", [(HEIGHT, WIDTH), (2 * HEIGHT, 2 * WIDTH)])
def test_edge_aware_smoothness_gradcheck(image_size):
    disp = uniform(2, 1, HEIGHT, WIDTH, low=0.1, high=1.0, seed=21)
    check(edge_aware_smoothness, disp, uniform(2, 3, *image_size, seed=22))


def test_kl_standard_normal_gradcheck():
    check(kl_standard_normal, uniform(2, 6, low=-1.0, high=1.0, seed=23), uniform(2, 6, low=-3.0, high=1.0, seed=24))


def test_wasserstein_losses_gradcheck():
    check(critic_loss, uniform(4, seed=25), uniform(4, seed=26))
    check(generator_loss, uniform(4, seed=27))


def test_gradient_penalty_gradcheck_and_gradgradcheck_in_the_critic_weights():
    """The penalty reaches the critic through a gradient (create_graph=True): check it and its own gradient."""
    real, fake = uniform(3, 1, 2, 2, seed=28).detach(), uniform(3, 1, 2, 2, seed=29).detach()

    def penalty(weight: torch.Tensor) -> torch.Tensor:
        torch.manual_seed(0)  # the interpolation weights: the same draw on every evaluation
        return gradient_penalty(lambda x: torch.tanh(x.flatten(1) @ weight).sum(1), real, fake, gamma=10.0)

    weight = uniform(4, 2, low=-1.0, high=1.0, seed=30)
    check(penalty, weight)
    assert gradgradcheck(penalty, (weight,), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_learned_intrinsics_gradcheck():
    from endoflow.models.intrinsics import correct_intrinsics

    check(lambda K, c: correct_intrinsics(K, c, (HEIGHT, WIDTH)), intrinsics(2),
          uniform(2, 4, low=-0.3, high=0.3, seed=31))


# ------------------------------------------------------------------------------------------- layers
@pytest.mark.parametrize("kernel, stride", [(3, 1), (3, 2), (1, 1)])
def test_gemm_weight_grad_convolution_gradcheck_and_gradgradcheck(kernel, stride):
    """On a map of few positions, where the weight's gradient is the layer's own matrix product."""
    conv = GemmWeightGradConv2d(3, 4, kernel, stride=stride, padding=kernel // 2).double()
    x = uniform(2, 3, 2 * stride, 2 * stride, low=-1.0, high=1.0, seed=40)
    assert conv._takes_gemm_weight_grad(x, conv.weight)

    def convolve(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        return conv._conv_forward(x, weight, bias)

    inputs = (x, variable(conv.weight), variable(conv.bias))
    check(convolve, *inputs)
    assert gradgradcheck(convolve, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)
