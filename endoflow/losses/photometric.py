"""Photometric reprojection losses: the paper's MSE and Monodepth2's SSIM + L1 with per-pixel minimum
over sources and auto-masking (Godard et al., "Digging into self-supervised monocular depth estimation").

Images are ``[B, C, H, W]`` with values in [0, 1]; per-pixel errors are ``[B, 1, H, W]`` (mean over
channels). :func:`view_synthesis_error` is the one ground-truth-free measure of depth and motion: how well a frame
is rebuilt from another (the held-out photometric error of validation, ``endoflow adapt`` and ``reconstruct``).
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F

from endoflow.config import LossConfig
from endoflow.geometry.warp import warp_frame
from endoflow.shapes import check_shape

# SSIM stabilisers for a dynamic range of 1 (Wang et al. 2004: (0.01 L)^2, (0.03 L)^2).
_C1 = 0.01**2
_C2 = 0.03**2
# Noise on the identity error breaks exact ties with the reprojection error (e.g. a static camera, where the
# warp returns the source) at random instead of always the same way.
_TIE_BREAK_STD = 1e-5
# A source's error where it does not see a pixel: above any photometric error, so the minimum takes another source
_UNSEEN_ERROR = 1e3
# Monodepth2's SSIM share, fixed: a measure compared across runs must not follow a run's loss settings
MEASURE_SSIM_WEIGHT = 0.85


def view_synthesis_error(target: torch.Tensor, source: torch.Tensor, depth: torch.Tensor,
                         T_source_target: torch.Tensor, K: torch.Tensor, in_view: torch.Tensor | None = None
                         ) -> torch.Tensor:
    """``[B]``: how far ``target`` is from ``source`` warped into it with the target's ``depth [B, 1, H, W]`` and
    ``T_source_target [B, 4, 4]`` (``K [B, 3, 3]`` or ``[1, 3, 3]``): the SSIM + L1 error (:func:`photometric_error`,
    SSIM share 0.85) averaged over the target pixels in view (``in_view [B, 1, H, W]`` bool, None: all) whose sample
    lands inside the source image and in its view. Unitless, lower is better; 0 where no pixel counts."""
    sizes = check_shape("target", target, "B,C,H,W")
    check_shape("depth", depth, "B,1,H,W", B=sizes["B"], H=sizes["H"], W=sizes["W"])
    K = K.expand(sizes["B"], 3, 3) if K.shape[0] == 1 else K
    if in_view is None:
        warped, counted = warp_frame(source, depth, T_source_target, K)
    else:  # the view mask rides along as one more channel: one projection and one sampling for both
        check_shape("in_view", in_view, "B,1,H,W", **{k: sizes[k] for k in ("B", "H", "W")})
        dtype = torch.promote_types(source.dtype, depth.dtype)  # a mask sampled in bf16 would round to 1 early
        both, lands = warp_frame(torch.cat([source.to(dtype), in_view.to(dtype)], dim=1), depth, T_source_target, K)
        warped, lands_in_view = both[:, :-1].to(source.dtype), both[:, -1:] > 0.999
        counted = lands & in_view & lands_in_view
    error = photometric_error(warped, target, "ssim_l1", MEASURE_SSIM_WEIGHT)
    return (error * counted).sum(dim=(1, 2, 3)) / counted.sum(dim=(1, 2, 3)).clamp(min=1)


def _local_mean(x: torch.Tensor) -> torch.Tensor:
    """3x3 box filter; reflection padding keeps the border statistics from seeing artificial zeros.

    Summed along rows, then columns, from shifted views: ``F.avg_pool2d(kernel_size=3, stride=1)`` to rounding,
    and on 2 CPU cores 10x faster forward and 2x with its backward at 64 px (torch 2.13's CPU pooling does not
    vectorise a window that slides by one)."""
    padded = F.pad(x, (1, 1, 1, 1), mode="reflect")
    rows = padded[..., :, :-2] + padded[..., :, 1:-1] + padded[..., :, 2:]
    return (rows[..., :-2, :] + rows[..., 1:-1, :] + rows[..., 2:, :]) / 9


def ssim_map(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM dissimilarity ``(1 - SSIM) / 2`` in [0, 1], ``[B, C, H, W]``, over 3x3 windows."""
    check_shape("y", y, "B,C,H,W", **check_shape("x", x, "B,C,H,W"))
    mu_x, mu_y = _local_mean(x), _local_mean(y)
    var_x = _local_mean(x * x) - mu_x * mu_x
    var_y = _local_mean(y * y) - mu_y * mu_y
    cov_xy = _local_mean(x * y) - mu_x * mu_y
    numerator = (2 * mu_x * mu_y + _C1) * (2 * cov_xy + _C2)
    denominator = (mu_x * mu_x + mu_y * mu_y + _C1) * (var_x + var_y + _C2)
    return ((1 - numerator / denominator) / 2).clamp(0, 1)


def held_out_photometric_error(target: torch.Tensor, sources: list[torch.Tensor], depth: torch.Tensor,
                               T_source_target: list[torch.Tensor], K: torch.Tensor,
                               in_view: torch.Tensor | None = None) -> torch.Tensor:
    """``[B]``: the photometric error of held-out frames, the one measure of depth and motion without ground truth
    (validation on unlabelled video, ``endoflow adapt``): each ``target`` rebuilt from each of its ``sources`` by
    :func:`view_synthesis_error` with the predicted ``depth`` and ``T_source_target`` (one per source), averaged
    over the sources. Unitless, lower is better."""
    if len(sources) != len(T_source_target) or not sources:
        raise ValueError(f"expected one pose per source, got {len(sources)} sources and {len(T_source_target)} poses")
    errors = [view_synthesis_error(target, source, depth, T, K, in_view) for source, T in zip(sources, T_source_target)]
    return torch.stack(errors).mean(dim=0)


def photometric_error(
    pred: torch.Tensor, target: torch.Tensor, kind: Literal["mse", "ssim_l1"], ssim_weight: float = 0.85
) -> torch.Tensor:
    """Per-pixel photometric error ``[B, 1, H, W]`` between two ``[B, C, H, W]`` images.

    ``mse``: squared difference (the paper's loss). ``ssim_l1``: ``ssim_weight * ssim_map + (1 -
    ssim_weight) * |pred - target|`` (Monodepth2, 0.85). Both averaged over channels.
    """
    check_shape("target", target, "B,C,H,W", **check_shape("pred", pred, "B,C,H,W"))
    if kind == "mse":
        return (pred - target).square().mean(1, keepdim=True)
    if kind == "ssim_l1":
        l1 = (pred - target).abs().mean(1, keepdim=True)
        ssim = ssim_map(pred, target).mean(1, keepdim=True)
        return ssim_weight * ssim + (1 - ssim_weight) * l1
    raise ValueError(f"photometric kind must be 'mse' or 'ssim_l1', got {kind!r}")


def _combine_over_sources(errors: list[torch.Tensor], use_minimum: bool) -> torch.Tensor:
    stacked = torch.cat(errors, dim=1)
    return stacked.min(dim=1, keepdim=True).values if use_minimum else stacked.mean(dim=1, keepdim=True)


@torch.no_grad()
def identity_error(target: torch.Tensor, sources: list[torch.Tensor], cfg: LossConfig) -> torch.Tensor:
    """Per-pixel error ``[B, 1, H, W]`` of the unwarped sources against the target, combined over sources as
    :func:`reprojection_loss` combines the warped ones (auto-masking's "no motion" reference)."""
    return _combine_over_sources(
        [photometric_error(s, target, cfg.photometric, cfg.ssim_weight) for s in sources], cfg.min_reprojection
    )


def reprojection_loss(
    warped: list[torch.Tensor],
    target: torch.Tensor,
    sources: list[torch.Tensor],
    cfg: LossConfig,
    identity: torch.Tensor | None = None,
    seen: list[torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Photometric reprojection loss of the target reconstructed from several sources.

    Args:
        warped: each source warped into the target view, ``[B, C, H, W]`` each.
        target: the target image ``[B, C, H, W]``.
        sources: the same sources unwarped, in the same order (used by auto-masking only).
        cfg: ``photometric`` and ``ssim_weight`` choose the per-pixel error; ``min_reprojection`` takes the
            per-pixel minimum over sources (else the mean); ``automask`` also computes the identity error of
            the unwarped sources (combined over sources the same way) and lets it win per pixel where it is
            lower: such pixels (static scenes, objects moving with the camera) give no gradient.
        identity: :func:`identity_error` of these sources, when the caller already has it (it depends on
            neither depth nor pose, so a multi-scale loss computes it once).
        seen: per warped source, ``[B, 1, H, W]`` bool: the target pixel is in the field of view and its
            warped sample lands in the source's (None: everywhere). A source counts only where it is seen, and
            the loss averages over the pixels some source sees; pixels no source sees give no gradient.

    Returns:
        ``loss`` (scalar, mean of the per-pixel map over the pixels seen), the per-pixel map ``[B, 1, H, W]``,
        and ``mask [B, 1, H, W]`` bool, True where the reprojection error is the one used (all True without
        auto-masking).
    """
    mismatched = (cfg.automask and len(sources) != len(warped)) or (seen is not None and len(seen) != len(warped))
    if not warped or mismatched:
        raise ValueError(f"expected at least one warped image and, with automask or seen masks, as many sources "
                         f"({len(warped)} warped, {len(sources)} sources)")
    errors = [photometric_error(w, target, cfg.photometric, cfg.ssim_weight) for w in warped]
    if seen is None:
        reprojection, any_seen = _combine_over_sources(errors, cfg.min_reprojection), None
    else:
        reprojection, any_seen = _combine_seen(errors, seen, cfg.min_reprojection)
    if cfg.automask:
        if identity is None:
            identity = identity_error(target, sources, cfg)
        identity = identity + _TIE_BREAK_STD * torch.randn_like(identity)
        mask = reprojection < identity
        per_pixel = torch.where(mask, reprojection, identity)
    else:
        per_pixel, mask = reprojection, torch.ones_like(reprojection, dtype=torch.bool)
    if any_seen is None:
        return per_pixel.mean(), per_pixel, mask
    loss = per_pixel[any_seen].mean() if any_seen.any() else per_pixel.sum() * 0
    return loss, per_pixel, mask & any_seen


def _combine_seen(errors: list[torch.Tensor], seen: list[torch.Tensor], use_minimum: bool
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_combine_over_sources` over the sources that see each pixel, and where any does."""
    stacked, visible = torch.cat(errors, dim=1), torch.cat(seen, dim=1)
    any_seen = visible.any(dim=1, keepdim=True)
    if use_minimum:
        unseen = torch.full_like(stacked, _UNSEEN_ERROR)
        combined = torch.where(visible, stacked, unseen).min(dim=1, keepdim=True).values
    else:
        combined = (stacked * visible).sum(dim=1, keepdim=True) / visible.sum(dim=1, keepdim=True).clamp(min=1)
    return combined, any_seen
