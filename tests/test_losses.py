"""Loss functions: photometric errors, reprojection with minimum and auto-masking, smoothness, KL, WGAN-GP."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from endoflow.config import LossConfig
from endoflow.geometry.pose import pose_vec_to_matrix
from endoflow.geometry.warp import warp_frame
from endoflow.losses.consistency import depth_inconsistency, geometry_consistency
from endoflow.losses.gan import critic_loss, generator_loss, gradient_penalty
from endoflow.losses.kl import kl_standard_normal
from endoflow.losses.photometric import (MEASURE_SSIM_WEIGHT, photometric_error, reprojection_loss, ssim_map,
                                         view_synthesis_error)
from endoflow.losses.smoothness import edge_aware_smoothness


def images(*shape: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed))


# ------------------------------------------------------------------------------------------------- SSIM
def test_ssim_dissimilarity_is_zero_for_identical_images_and_bounded() -> None:
    x, y = images(2, 3, 8, 8), images(2, 3, 8, 8, seed=1)
    assert torch.allclose(ssim_map(x, x), torch.zeros_like(x), atol=1e-6)
    d = ssim_map(x, y)
    assert d.shape == x.shape and (d >= 0).all() and (d <= 1).all() and d.mean() > 0.1


def test_ssim_matches_the_formula_on_a_3x3_window() -> None:
    x, y = images(1, 1, 5, 5, seed=2), images(1, 1, 5, 5, seed=3)
    wx, wy = x[0, 0, 1:4, 1:4].double(), y[0, 0, 1:4, 1:4].double()  # window around interior pixel (2, 2)
    mx, my = wx.mean(), wy.mean()
    vx, vy = (wx * wx).mean() - mx**2, (wy * wy).mean() - my**2
    cxy = (wx * wy).mean() - mx * my
    c1, c2 = 0.01**2, 0.03**2
    ssim = (2 * mx * my + c1) * (2 * cxy + c2) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    assert ssim_map(x, y)[0, 0, 2, 2].item() == pytest.approx(float((1 - ssim) / 2), abs=1e-6)


def test_ssim_border_uses_reflection_padding() -> None:
    x, y = images(1, 1, 4, 4, seed=4), images(1, 1, 4, 4, seed=5)
    # The corner's window is the 2x2 corner block plus its mirror images: the same window that an
    # explicitly reflection-padded image has around its (1, 1).
    padded_x, padded_y = (torch.nn.functional.pad(t, (1, 1, 1, 1), mode="reflect") for t in (x, y))
    corner = ssim_map(padded_x, padded_y)[0, 0, 1, 1]
    assert ssim_map(x, y)[0, 0, 0, 0].item() == pytest.approx(corner.item(), abs=1e-6)


def test_ssim_is_monodepth2s_average_pooled_ssim_to_rounding() -> None:
    x, y = images(4, 3, 64, 64, seed=6), images(4, 3, 64, 64, seed=7)

    def pooled(t: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.avg_pool2d(torch.nn.functional.pad(t, (1, 1, 1, 1), mode="reflect"), 3, 1)

    mu_x, mu_y = pooled(x), pooled(y)
    numerator = (2 * mu_x * mu_y + 0.01**2) * (2 * (pooled(x * y) - mu_x * mu_y) + 0.03**2)
    denominator = (mu_x**2 + mu_y**2 + 0.01**2) * (pooled(x * x) - mu_x**2 + pooled(y * y) - mu_y**2 + 0.03**2)
    reference = ((1 - numerator / denominator) / 2).clamp(0, 1)
    assert torch.allclose(ssim_map(x, y), reference, rtol=0, atol=1e-5)


# -------------------------------------------------------------------------------------- photometric
def test_photometric_error_kinds() -> None:
    x, y = images(2, 3, 6, 6), images(2, 3, 6, 6, seed=1)
    mse = photometric_error(x, y, "mse")
    assert mse.shape == (2, 1, 6, 6)
    assert torch.allclose(mse, ((x - y) ** 2).mean(1, keepdim=True))
    l1 = (x - y).abs().mean(1, keepdim=True)
    assert torch.allclose(photometric_error(x, y, "ssim_l1", ssim_weight=0.0), l1)
    assert torch.allclose(photometric_error(x, y, "ssim_l1", ssim_weight=1.0), ssim_map(x, y).mean(1, keepdim=True))
    mixed = photometric_error(x, y, "ssim_l1", ssim_weight=0.85)
    assert torch.allclose(mixed, 0.85 * ssim_map(x, y).mean(1, keepdim=True) + 0.15 * l1)
    with pytest.raises(ValueError, match="kind"):
        photometric_error(x, y, "l2")


# ------------------------------------------------------------------------------------- reprojection
def config(**changes) -> LossConfig:
    return LossConfig(**changes)


def test_minimum_over_sources_picks_the_better_reconstruction_per_pixel() -> None:
    target = images(1, 3, 8, 8)
    good, bad = target.clone(), images(1, 3, 8, 8, seed=1)
    good[..., :4] = bad[..., :4]  # the left half is explained by neither; the right half only by `good`
    bad[..., :4] = target[..., :4]  # now `bad` explains the left half
    cfg = config(photometric="mse", automask=False, min_reprojection=True)
    loss, per_pixel, mask = reprojection_loss([good, bad], target, [], cfg)
    assert loss.item() == pytest.approx(0.0, abs=1e-12) and mask.all()
    mean_cfg = config(photometric="mse", automask=False, min_reprojection=False)
    mean_loss, _, _ = reprojection_loss([good, bad], target, [], mean_cfg)
    expected = (((bad - target) ** 2).mean() + ((good - target) ** 2).mean()) / 2
    assert mean_loss.item() == pytest.approx(expected.item())
    assert per_pixel.shape == (1, 1, 8, 8)


def test_automask_drops_pixels_where_the_unwarped_source_already_matches() -> None:
    target = images(2, 3, 8, 8)
    static_source = target.clone()  # e.g. the camera did not move
    poor_warp = (target + 0.2 * images(2, 3, 8, 8, seed=1)).requires_grad_()
    loss, per_pixel, mask = reprojection_loss([poor_warp], target, [static_source], config())
    assert not mask.any()
    assert loss.item() == pytest.approx(0.0, abs=1e-4)
    loss.backward()
    assert poor_warp.grad is None or poor_warp.grad.abs().sum() == 0


def test_automask_keeps_pixels_the_warp_explains_and_gradients_reach_them() -> None:
    target = images(1, 3, 8, 8)
    moved_source = images(1, 3, 8, 8, seed=1)
    warp = (target + 0.01 * images(1, 3, 8, 8, seed=2)).requires_grad_()
    loss, per_pixel, mask = reprojection_loss([warp], target, [moved_source], config(photometric="mse"))
    assert mask.all() and mask.dtype == torch.bool and mask.shape == (1, 1, 8, 8)
    assert torch.allclose(per_pixel, photometric_error(warp, target, "mse").detach())
    loss.backward()
    assert warp.grad.abs().sum() > 0


def test_reprojection_loss_is_continuous_minimum_of_identity_and_warp() -> None:
    # A worse warp can never give a lower loss than the identity error: what the masked pixels
    # contribute is the identity error, not zero.
    target, source = images(1, 3, 16, 16), images(1, 3, 16, 16, seed=1)
    identity_only, _, _ = reprojection_loss([source], target, [source], config(photometric="mse"))
    terrible, _, mask = reprojection_loss([1 - target], target, [source], config(photometric="mse"))
    assert terrible.item() <= identity_only.item() + 1e-4
    assert terrible.item() > 0.5 * identity_only.item() and not mask.all()


def test_the_view_synthesis_error_counts_the_pixels_whose_sample_lands_in_view() -> None:
    # what the error is: SSIM + L1 averaged over target pixels in view whose sample lands inside the source and in
    # its view (the mask warped as the image is), written out with one warp for each
    target, source = images(2, 3, 24, 24), images(2, 3, 24, 24, seed=1)
    depth = 2 + images(2, 1, 24, 24, seed=2)
    v, u = torch.meshgrid(torch.arange(24.0), torch.arange(24.0), indexing="ij")
    in_view = ((u - 11.5) ** 2 + (v - 11.5) ** 2 <= 10**2).expand(2, 1, 24, 24)
    T_source_target = pose_vec_to_matrix(torch.tensor([[0.05, -0.02, 0.1, 0.01, 0.02, -0.01],
                                                       [-0.03, 0.04, -0.05, 0.0, -0.02, 0.03]]))
    K = torch.tensor([[[20.0, 0.0, 11.5], [0.0, 20.0, 11.5], [0.0, 0.0, 1.0]]])
    warped, lands = warp_frame(source, depth, T_source_target, K.expand(2, 3, 3))
    lands_in_view = warp_frame(in_view.float(), depth, T_source_target, K.expand(2, 3, 3))[0] > 0.999
    counted = lands & in_view & lands_in_view
    error = photometric_error(warped, target, "ssim_l1", MEASURE_SSIM_WEIGHT)
    expected = (error * counted).sum(dim=(1, 2, 3)) / counted.sum(dim=(1, 2, 3))
    assert (lands & in_view & ~lands_in_view).any()  # some samples land in the image but outside its view
    assert torch.equal(view_synthesis_error(target, source, depth, T_source_target, K, in_view), expected)


# --------------------------------------------------------------------------------------- smoothness
def test_smoothness_is_zero_for_constant_disparity_and_scale_invariant() -> None:
    image = images(2, 3, 10, 10)
    assert edge_aware_smoothness(torch.full((2, 1, 10, 10), 0.3), image).item() == pytest.approx(0.0, abs=1e-7)
    disp = 0.1 + images(2, 1, 10, 10, seed=1)
    scaled = edge_aware_smoothness(5 * disp, image).item()
    assert scaled == pytest.approx(edge_aware_smoothness(disp, image).item(), rel=1e-5)


def test_smoothness_penalises_disparity_edges_less_where_the_image_has_edges() -> None:
    disp = torch.ones(1, 1, 8, 8)
    disp[..., 4:] = 2.0  # a depth discontinuity between columns 3 and 4
    flat = torch.full((1, 3, 8, 8), 0.5)
    edge = flat.clone()
    edge[..., 4:] = 1.0  # an image edge in the same place
    assert edge_aware_smoothness(disp, edge) < edge_aware_smoothness(disp, flat)


def test_smoothness_resizes_a_larger_image_to_the_disparity() -> None:
    image = images(1, 3, 16, 16)
    disp = 0.1 + images(1, 1, 8, 8, seed=1)
    pooled = torch.nn.functional.avg_pool2d(image, 2)
    assert edge_aware_smoothness(disp, image).item() == pytest.approx(edge_aware_smoothness(disp, pooled).item())


# ----------------------------------------------------------------------------------------------- KL
def test_kl_is_zero_at_the_prior_and_positive_elsewhere() -> None:
    zeros = torch.zeros(3, 6)
    assert torch.equal(kl_standard_normal(zeros, zeros), torch.zeros(3))
    kl = kl_standard_normal(torch.randn(3, 6), torch.randn(3, 6))
    assert kl.shape == (3,) and (kl > 0).all()


def test_kl_closed_form_matches_monte_carlo() -> None:
    generator = torch.Generator().manual_seed(0)
    mean = torch.tensor([[0.5, -1.0, 0.0, 0.2, 0.0, 1.5], [0.0, 0.3, -0.4, 0.0, 0.8, 0.0]], dtype=torch.float64)
    logvar = torch.tensor([[0.0, -1.0, 0.5, -0.3, 0.2, 0.0], [-2.0, 0.0, 0.4, 0.1, -0.5, 0.3]], dtype=torch.float64)
    std = (0.5 * logvar).exp()
    samples = mean + std * torch.randn(200_000, *mean.shape, generator=generator, dtype=torch.float64)
    log_q = torch.distributions.Normal(mean, std).log_prob(samples).sum(-1)
    log_p = torch.distributions.Normal(0.0, 1.0).log_prob(samples).sum(-1)
    monte_carlo = (log_q - log_p).mean(0)
    assert torch.allclose(kl_standard_normal(mean, logvar), monte_carlo, rtol=0.02)


def test_kl_gradients_reach_mean_and_logvar() -> None:
    mean, logvar = torch.randn(4, 6, requires_grad=True), torch.randn(4, 6, requires_grad=True)
    kl_standard_normal(mean, logvar).mean().backward()
    assert torch.allclose(mean.grad, mean.detach() / 4)
    assert torch.allclose(logvar.grad, 0.5 * (logvar.detach().exp() - 1) / 4)


# ---------------------------------------------------------------------------------------------- GAN
def test_wasserstein_losses() -> None:
    real, fake = torch.tensor([2.0, 4.0]), torch.tensor([-1.0, 0.0])
    assert critic_loss(real, fake).item() == pytest.approx(-3.5)
    assert generator_loss(fake).item() == pytest.approx(0.5)


def linear_critic(weight_norm: float) -> torch.nn.Module:
    critic = torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(2 * 4 * 4, 1))
    with torch.no_grad():
        critic[1].weight.copy_(torch.randn(1, 32))
        critic[1].weight.mul_(weight_norm / critic[1].weight.norm())
    return critic


def test_gradient_penalty_vanishes_for_a_unit_gradient_critic() -> None:
    real, fake = torch.randn(5, 2, 4, 4), torch.randn(5, 2, 4, 4)
    assert gradient_penalty(linear_critic(1.0), real, fake, gamma=10.0).item() == pytest.approx(0.0, abs=1e-8)
    # The gradient norm is 3 everywhere: penalty = gamma * (3 - 1)^2.
    assert gradient_penalty(linear_critic(3.0), real, fake, gamma=10.0).item() == pytest.approx(40.0, rel=1e-5)


def test_gradient_penalty_trains_the_critic_only() -> None:
    critic = torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(32, 16), torch.nn.Tanh(), torch.nn.Linear(16, 1))
    generator_weight = torch.ones(1, requires_grad=True)
    real, fake = torch.randn(6, 2, 4, 4), generator_weight * torch.randn(6, 2, 4, 4)
    penalty = gradient_penalty(critic, real, fake, gamma=10.0)
    assert penalty.item() > 0
    penalty.backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in critic.parameters() if p.ndim == 2)
    assert generator_weight.grad is None


@pytest.mark.parametrize("seed", [0, 1])
def test_penalty_interpolates_between_real_and_fake(seed: int) -> None:
    torch.manual_seed(seed)
    seen = []
    real, fake = torch.zeros(64, 1), torch.ones(64, 1)

    def recording_critic(x: torch.Tensor) -> torch.Tensor:
        seen.append(x.detach())
        return x.sum(1)

    gradient_penalty(recording_critic, real, fake, gamma=1.0)
    values = seen[0].numpy()
    assert ((values >= 0) & (values <= 1)).all() and np.std(values) > 0.1


def bumpy_depth(height: int = 16, width: int = 20) -> torch.Tensor:
    """A tilted, rippled surface 2-4 cm away: ``[1, 1, H, W]``."""
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                          indexing="ij")
    return (2.5 + 0.03 * u + 0.4 * torch.sin(u / 3) * torch.cos(v / 4))[None, None]


def camera(height: int = 16, width: int = 20) -> torch.Tensor:
    return torch.tensor([[[18.0, 0.0, (width - 1) / 2], [0.0, 18.0, (height - 1) / 2], [0.0, 0.0, 1.0]]],
                        dtype=torch.float64)


def source_depth_seeing(depth_tgt: torch.Tensor, T_src_tgt: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """The exact source-frame depth of a fronto-parallel plane after a pure move along the view: the plane at ``d``
    seen from the source camera, where target points have z ``d + t_z`` (``t_z`` of ``T_src_tgt``)."""
    return depth_tgt + T_src_tgt[:, 2, 3].reshape(-1, 1, 1, 1)


def test_consistent_depths_give_zero_and_the_loss_grows_with_disagreement() -> None:
    plane = torch.full((1, 1, 16, 20), 3.0, dtype=torch.float64)
    forward = pose_vec_to_matrix(torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, -0.2]], dtype=torch.float64))
    K = camera()
    seen = source_depth_seeing(plane, forward, K)
    difference, valid = depth_inconsistency(plane, seen, forward, K)
    assert valid.any() and difference.abs().max() < 1e-9
    assert geometry_consistency(plane, [seen], [forward], K) < 1e-9
    worse = [geometry_consistency(plane, [seen * factor], [forward], K).item() for factor in (1.05, 1.2, 1.5)]
    assert 0 < worse[0] < worse[1] < worse[2]
    # |a - b| / (a + b): a depth 1.2 times the truth gives 0.2 / 2.2
    assert worse[1] == pytest.approx(0.2 / 2.2, rel=1e-6)


def test_the_identity_pose_compares_a_frame_with_itself_at_any_common_scale() -> None:
    depth, K, identity = bumpy_depth(), camera(), torch.eye(4, dtype=torch.float64)[None]
    assert geometry_consistency(depth, [depth], [identity], K) < 1e-9
    # one scale for both frames and the path: nothing to disagree about
    assert geometry_consistency(3.7 * depth, [3.7 * depth], [identity], K) < 1e-9
    assert geometry_consistency(depth, [1.1 * depth], [identity], K) == pytest.approx(0.1 / 2.1, rel=1e-6)


def test_points_that_leave_the_source_image_count_for_nothing() -> None:
    depth, K = bumpy_depth(), camera()
    sideways = pose_vec_to_matrix(torch.tensor([[0.0, 0.0, 0.0, 1e3, 0.0, 0.0]], dtype=torch.float64))
    difference, valid = depth_inconsistency(depth, depth, sideways, K)
    assert not valid.any() and (difference == 0).all()
    assert geometry_consistency(depth, [depth], [sideways], K) == 0


def test_consistency_refuses_mismatched_sources_and_shapes() -> None:
    depth, K, identity = bumpy_depth(), camera(), torch.eye(4, dtype=torch.float64)[None]
    with pytest.raises(ValueError, match="one pose per source"):
        geometry_consistency(depth, [depth, depth], [identity], K)
    with pytest.raises(ValueError, match="depth_src"):
        depth_inconsistency(depth, depth[..., :-1], identity, K)
