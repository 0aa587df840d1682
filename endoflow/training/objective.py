"""The self-supervised training objective (paper eq. 3, with Monodepth2's options).

For a target frame ``cur`` and its neighbours ``prev`` and ``next``:

- DepthNet predicts disparity at each scale; with ``loss.multiscale`` every scale's disparity is upsampled
  to full resolution before it becomes depth (Monodepth2), else only scale 0 is used.
- PoseNet gives ``T_prev_cur`` and ``T_next_cur`` (sampled in training mode with the pose VAE, see
  :mod:`endoflow.models.endoflow_model`); both neighbours are warped into ``cur`` with ``warp_frame`` at full
  resolution and the intrinsics ``K`` of the stored size.
- ``photometric``: :func:`reprojection_loss` (MSE as the paper, or SSIM + L1; per-pixel minimum and
  auto-masking as ``loss.*`` says), averaged over scales.
  With ``loss.automask`` on and ``loss.automask_pose`` off, the depth (and a learned ``K``) take the gradient of the
  masked loss and the pose that of the unmasked one (every warp made twice: once with the pose detached, once with
  the depth detached); the value is the masked loss's (:func:`reprojection`). With ``loss.automask_pose_spread``
  the pose's sampling spread keeps the masked loss's gradient and only its mean takes the unmasked one;
  ``loss.pose_ssim_weight`` sets SSIM's share in the unmasked one. ``loss.automask_depth`` off is the reverse split:
  the pose keeps the masked loss and the depth (and ``K``) takes the unmasked one (:func:`split_reprojection`); the
  config refuses both off (that trains as ``loss.automask`` off).
- ``smoothness``: edge-aware smoothness of each scale's disparity, divided by ``2^scale``, averaged.
- ``kl``: the closed-form KL of both predicted pose distributions to N(0, I), summed over the two poses,
  averaged over the batch (zero without the pose VAE).
- ``geometry``: with ``loss.geometry_weight`` > 0, DepthNet also predicts both neighbours' depth and
  :func:`~endoflow.losses.consistency.geometry_consistency` compares it with the target's depth moved by the
  predicted poses (scale 0), so that depth and path keep one scale over a video (else absent, and no extra pass).
- ``total = photometric + loss.smoothness_weight * smoothness + loss.kl_weight * kl + loss.geometry_weight *
  geometry`` (``kl_weight`` is beta; :func:`loss_weights`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from endoflow.config import LossConfig
from endoflow.geometry.warp import warp_frame
from endoflow.losses.consistency import geometry_consistency
from endoflow.losses.kl import kl_standard_normal
from endoflow.losses.photometric import identity_error, reprojection_loss
from endoflow.losses.smoothness import edge_aware_smoothness
from endoflow.models.endoflow_model import EndoflowModel, PoseEstimate
from endoflow.shapes import check_shape

REQUIRED_KEYS = ("prev", "cur", "next", "K")


def loss_weights(loss_cfg: LossConfig) -> dict[str, float]:
    """The weight in the total of each term computed: the photometric loss first, the geometry consistency only
    where its weight is not 0 (it costs a depth pass over both neighbours); a KL weighted 0 is still computed."""
    weights = {"photometric": 1.0, "smoothness": loss_cfg.smoothness_weight, "kl": loss_cfg.kl_weight}
    if loss_cfg.geometry_weight > 0:
        weights["geometry"] = loss_cfg.geometry_weight
    return weights


def _check_batch(batch: dict) -> None:
    missing = [k for k in REQUIRED_KEYS if k not in batch]
    if missing:
        raise ValueError(f"batch lacks {missing}; expected the loader's keys {list(REQUIRED_KEYS)}")
    sizes = check_shape("batch['cur']", batch["cur"], "B,3,H,W")
    for key in ("prev", "next"):
        check_shape(f"batch[{key!r}]", batch[key], "B,3,H,W", **sizes)
    check_shape("batch['K']", batch["K"], "B,3,3", **sizes)


def pose_kl(poses: list[PoseEstimate]) -> torch.Tensor:
    """Batch mean of the summed KL of the pose distributions (0 when they are deterministic)."""
    terms = [kl_standard_normal(p.mean, p.logvar) for p in poses if p.logvar is not None]
    if not terms:
        return poses[0].mean.new_zeros(())
    return torch.stack(terms).sum(dim=0).mean()


def reprojection(
    target: torch.Tensor,
    sources: list[torch.Tensor],
    depth: torch.Tensor,
    T_source_target: list[torch.Tensor],
    K: torch.Tensor,
    loss_cfg: LossConfig,
    identity: torch.Tensor | None = None,
    valid: torch.Tensor | None = None,
    T_masked: list[torch.Tensor] | None = None,
) -> torch.Tensor:
    """Photometric loss of ``target [B, 3, H, W]`` rebuilt from each source with target ``depth [B, 1, H, W]``
    and ``T_source_target[i] [B, 4, 4]`` (one per source), as ``loss_cfg`` says; ``identity`` as
    :func:`reprojection_loss` takes it. ``valid [B, 1, H, W]`` bool: the field of view, the same in every frame of
    a sequence (None: everywhere); a source counts where the target pixel is in it and lands in it.

    With ``automask`` on and ``automask_pose`` or ``automask_depth`` off, the loss is split
    (:func:`split_reprojection`). ``T_masked``, equal in value to ``T_source_target``, is what the masked loss
    warps with where the mask spares the pose (None: the poses detached), so that a part of the pose can keep the
    mask's gradient."""
    if loss_cfg.automask and not (loss_cfg.automask_pose and loss_cfg.automask_depth):
        return split_reprojection(target, sources, depth, T_source_target, K, loss_cfg, identity, valid, T_masked)
    warped = [warp_frame(src, depth, T, K)[0] for src, T in zip(sources, T_source_target)]
    seen = None
    if valid is not None:
        inside = valid.to(depth.dtype)
        # bilinear samples of the mask: a warped sample is in view where all four pixels around it are
        seen = [valid & (warp_frame(inside, depth, T, K)[0] > 0.999) for T in T_source_target]
        # SSIM's windows reach a pixel's neighbours: those out of view take part as values, not as gradient
        warped = [torch.where(s, w, w.detach()) for w, s in zip(warped, seen)]
    return reprojection_loss(warped, target, sources, loss_cfg, identity, seen)[0]


def split_reprojection(
    target: torch.Tensor,
    sources: list[torch.Tensor],
    depth: torch.Tensor,
    T_source_target: list[torch.Tensor],
    K: torch.Tensor,
    loss_cfg: LossConfig,
    identity: torch.Tensor | None,
    valid: torch.Tensor | None,
    T_masked: list[torch.Tensor] | None,
) -> torch.Tensor:
    """:func:`reprojection` with auto-masking kept for one of pose and depth: the part whose ``automask_*`` is on
    takes the gradient of the masked loss, the other that of the same reprojection error without the mask.

    - ``automask_pose`` off: auto-masking hands a pixel to the unwarped neighbour exactly where a wrong motion warps
      worse than none, which would leave the pose no gradient there.
    - ``automask_depth`` off: the lumen's far end barely moves between frames, so the mask drops it from the depth's
      loss as well.

    The depth and a learned ``K`` go together. The value is the masked loss's, so that runs compare; the unmasked
    loss gives SSIM the share ``pose_ssim_weight`` where the pose learns from it (None: ``ssim_weight``)."""
    pose_free, depth_free = not loss_cfg.automask_pose, not loss_cfg.automask_depth
    detached = [T.detach() for T in T_source_target]
    if T_masked is None:
        T_masked = detached if pose_free else T_source_target
    masked_depth, masked_K = (depth.detach(), K.detach()) if depth_free else (depth, K)
    masked = reprojection(target, sources, masked_depth, T_masked, masked_K,
                          loss_cfg.replace(automask_pose=True, automask_depth=True), identity, valid)
    ssim = loss_cfg.pose_ssim_weight if pose_free and loss_cfg.pose_ssim_weight is not None else loss_cfg.ssim_weight
    unmasked = reprojection(target, sources, depth if depth_free else depth.detach(),
                            T_source_target if pose_free else detached, K if depth_free else K.detach(),
                            loss_cfg.replace(automask=False, ssim_weight=ssim), None, valid)
    return masked + (unmasked - unmasked.detach())


def training_step_losses(model: EndoflowModel, batch: dict, loss_cfg: LossConfig) -> dict[str, torch.Tensor]:
    """Losses of one batch (keys as the loader's: ``prev``, ``cur``, ``next`` ``[B, 3, H, W]`` in [0, 1],
    ``K [B, 3, 3]``, and ``valid [B, 1, H, W]``, the field of view, where the shards have it: pixels outside it
    take part in neither the photometric nor the smoothness term).

    Returns:
        ``total`` (what to back-propagate), each term of :func:`loss_weights`, and per scale s ``photometric/s``
        and ``smoothness/s``; all scalars.
    """
    _check_batch(batch)
    cur, sources = batch["cur"], [batch["prev"], batch["next"]]
    K = model.camera_K(batch).to(cur.dtype)  # a camera nobody calibrated: its learned K
    disps = model.depth_net(cur)
    poses = [
        model.source_pose(cur, batch["prev"], source_is_next=False),
        model.source_pose(cur, batch["next"], source_is_next=True),
    ]
    scales = range(len(disps)) if loss_cfg.multiscale else range(1)
    identity = identity_error(cur, sources, loss_cfg) if loss_cfg.automask else None
    valid = batch.get("valid")
    if valid is not None and bool(valid.all()):
        valid = None  # every pixel in view (the built-in data): the plain means, the same loss to the bit
    transforms, masked_transforms = warp_transforms(poses, loss_cfg)
    out: dict[str, torch.Tensor] = {}
    photometric, smoothness = [], []
    for s in scales:
        disp = disps[s]
        if disp.shape[-2:] != cur.shape[-2:]:
            disp = F.interpolate(disp, size=cur.shape[-2:], mode="bilinear", align_corners=False)
        loss = reprojection(cur, sources, model.disp_to_depth(disp), transforms, K, loss_cfg, identity, valid,
                            masked_transforms)
        smooth = edge_aware_smoothness(disps[s], cur, valid) / 2**s
        out[f"photometric/{s}"], out[f"smoothness/{s}"] = loss, smooth
        photometric.append(loss)
        smoothness.append(smooth)
    out["photometric"] = torch.stack(photometric).mean()
    out["smoothness"] = torch.stack(smoothness).mean()
    out["kl"] = pose_kl(poses)
    weights = loss_weights(loss_cfg)
    if "geometry" in weights:
        out["geometry"] = neighbour_consistency(model, disps[0], sources, poses, K, valid)
    total = out["photometric"]
    for term in list(weights)[1:]:
        total = total + weights[term] * out[term]
    out["total"] = total
    return out


def warp_transforms(poses: list[PoseEstimate], loss_cfg: LossConfig
                    ) -> tuple[list[torch.Tensor], list[torch.Tensor] | None]:
    """The transforms :func:`reprojection` warps with, and those its masked loss warps with where the mask spares the
    pose (None: the first, detached). With ``automask_pose_spread`` the pose's spread stays with the masked loss
    and its mean goes to the unmasked one."""
    if loss_cfg.automask and not loss_cfg.automask_pose and loss_cfg.automask_pose_spread:
        spread, mean = zip(*(pose.spread_and_mean_parts() for pose in poses))
        return list(mean), list(spread)
    return [pose.T_source_target for pose in poses], None


def neighbour_consistency(model: EndoflowModel, disp_cur: torch.Tensor, sources: list[torch.Tensor],
                          poses: list[PoseEstimate], K: torch.Tensor, valid: torch.Tensor | None) -> torch.Tensor:
    """:func:`geometry_consistency` of the target's full-resolution depth (from its scale-0 disparity) with each
    source's own predicted depth, through the poses that warp the sources, inside the field of view ``valid``."""
    depth_cur = model.disp_to_depth(disp_cur)
    depth_sources = [model.predict_depth(source) for source in sources]
    return geometry_consistency(depth_cur, depth_sources, [pose.T_source_target for pose in poses], K, valid)
