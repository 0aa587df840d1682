"""Edge-aware disparity smoothness (Monodepth2): disparity gradients are penalised less across image edges."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from endoflow.shapes import check_shape


def edge_aware_smoothness(disp: torch.Tensor, image: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """Scalar ``mean(|dx d| exp(-|dx I|)) + mean(|dy d| exp(-|dy I|))`` on mean-normalised disparity.

    Args:
        disp: ``[B, 1, h, w]`` disparity (any positive scale: it is divided by its per-image mean, so the
            loss does not reward shrinking the depth scale).
        image: ``[B, C, H, W]`` colour image; resized to ``(h, w)`` by area averaging when larger, so a
            coarse scale's disparity can be paired with the full-resolution image.
        valid: ``[B, 1, H, W]`` bool, the field of view (None: everywhere): only neighbours both inside it count
            (a coarse pixel is inside where all it covers is), and the mean disparity is theirs.
    """
    sizes = check_shape("disp", disp, "B,1,H,W")
    check_shape("image", image, "B,C,h,w", B=sizes["B"])  # any size: resized to the disparity's below
    if image.shape[-2:] != disp.shape[-2:]:
        image = F.interpolate(image, size=disp.shape[-2:], mode="area")
    grad_image_x = (image[..., :, 1:] - image[..., :, :-1]).abs().mean(1, keepdim=True)
    grad_image_y = (image[..., 1:, :] - image[..., :-1, :]).abs().mean(1, keepdim=True)
    if valid is None:
        normalised = disp / (disp.mean(dim=(2, 3), keepdim=True) + 1e-7)
        grad_disp_x = (normalised[..., :, 1:] - normalised[..., :, :-1]).abs()
        grad_disp_y = (normalised[..., 1:, :] - normalised[..., :-1, :]).abs()
        return (grad_disp_x * torch.exp(-grad_image_x)).mean() + (grad_disp_y * torch.exp(-grad_image_y)).mean()
    check_shape("valid", valid, "B,1,h,w", B=sizes["B"])
    # the coarse mask is found in float32: in bfloat16 0.999 rounds to 1 and no pixel would count as inside
    inside = valid.float()
    if inside.shape[-2:] != disp.shape[-2:]:
        inside = (F.interpolate(inside, size=disp.shape[-2:], mode="area") > 0.999).float()
    inside = inside.to(disp.dtype)
    mean = (disp * inside).sum(dim=(2, 3), keepdim=True) / inside.sum(dim=(2, 3), keepdim=True).clamp(min=1)
    normalised = disp / (mean + 1e-7)
    pairs_x = inside[..., :, 1:] * inside[..., :, :-1]
    pairs_y = inside[..., 1:, :] * inside[..., :-1, :]
    grad_disp_x = (normalised[..., :, 1:] - normalised[..., :, :-1]).abs()
    grad_disp_y = (normalised[..., 1:, :] - normalised[..., :-1, :]).abs()
    return ((grad_disp_x * torch.exp(-grad_image_x) * pairs_x).sum() / pairs_x.sum().clamp(min=1)
            + (grad_disp_y * torch.exp(-grad_image_y) * pairs_y).sum() / pairs_y.sum().clamp(min=1))
