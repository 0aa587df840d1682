"""Camera intrinsics learned from video: per camera, corrections of the pinhole K assumed for it.

A camera nobody calibrated gets an assumed K (a centred pinhole of ``data.assumed_fov_deg`` across its diagonal,
:func:`endoflow.data.intrinsics.assumed_intrinsics`); training corrects it with the view-synthesis loss, as Gordon et
al. ("Depth from Videos in the Wild", ICCV 2019) learn a camera's intrinsics from its video. One camera per dataset
(:data:`~endoflow.config.DATASETS`: a root of videos is one endoscope), four numbers each, so the module's shape never
depends on the data and every model file holds it:

- ``fx = fx_assumed * exp(a)``, ``fy = fy_assumed * exp(b)``: log-scale factors, so a focal length stays positive and
  a step means the same relative change at any size;
- ``cx = cx_assumed + c * width``, ``cy = cy_assumed + d * height``: the principal point's shift as a share of the
  image, so one camera's numbers hold at every image size.

All four start at 0 (the assumed K). Only samples whose K is unknown take the learned one (``intrinsics_known``
False); a calibrated camera's K is used as given. :meth:`CameraIntrinsics.learn` says whether training moves them,
and whether the principal point too (``train.intrinsics_principal_point``: under forward motion it is confounded
with the direction of travel, docs/results.md). Why parameters rather than a head predicting K from frames, and
what it recovers: docs/method.md, "Intrinsics learned from the video".
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import nn

from endoflow.shapes import check_shape


class CameraIntrinsics(nn.Module):
    """``corrections [cameras, 4]``: ``(log fx factor, log fy factor, cx shift, cy shift)`` per camera."""

    def __init__(self, cameras: int) -> None:
        super().__init__()
        self.corrections = nn.Parameter(torch.zeros(cameras, 4))
        self._centre_held: Optional[torch.utils.hooks.RemovableHandle] = None

    def learn(self, enabled: bool, principal_point: bool = True) -> None:
        """Whether gradients reach the corrections, and with ``principal_point`` False only the focal lengths' (the
        principal point's gradient is zeroed, so an optimiser without weight decay leaves it where it is)."""
        self.corrections.requires_grad_(enabled)
        if self._centre_held is not None:
            self._centre_held.remove()
            self._centre_held = None
        if enabled and not principal_point:
            focal_only = torch.tensor([1.0, 1.0, 0.0, 0.0])
            self._centre_held = self.corrections.register_hook(lambda grad: grad * focal_only.to(grad))

    def forward(self, K: torch.Tensor, camera: torch.Tensor, known: torch.Tensor, size: tuple[int, int]
                ) -> torch.Tensor:
        """``K [B, 3, 3]`` where ``known [B]`` (bool) says so, else the learned K of the sample's ``camera [B]``
        (int64) corrected from the assumed ``K``, for images of ``size`` ``(height, width)``; float32."""
        sizes = check_shape("K", K, "B,3,3")
        check_shape("camera", camera, "B", **sizes)
        check_shape("known", known, "B", **sizes)
        K = K.float()
        if bool(known.all()):
            return K  # nothing to learn: no graph through the corrections
        return torch.where(known[:, None, None], K, self.corrected(K, camera, size))

    def corrected(self, K: torch.Tensor, camera: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        """``K [B, 3, 3]`` corrected by the learned numbers of each sample's ``camera [B]``."""
        return correct_intrinsics(K, self.corrections[camera].to(K.dtype), size)

    def learned(self, camera: int) -> bool:
        """Whether training moved this camera's K from the assumed one."""
        return bool(self.corrections[camera].detach().abs().max() > 0)


def correct_intrinsics(K: torch.Tensor, corrections: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """``K [B, 3, 3]`` with ``corrections [B, 4]`` (module docstring) applied, for images of ``size``
    ``(height, width)``."""
    sizes = check_shape("K", K, "B,3,3")
    check_shape("corrections", corrections, "B,4", **sizes)
    height, width = size
    out = K.clone()
    out[:, 0, 0] = K[:, 0, 0] * torch.exp(corrections[:, 0])
    out[:, 1, 1] = K[:, 1, 1] * torch.exp(corrections[:, 1])
    out[:, 0, 2] = K[:, 0, 2] + corrections[:, 2] * width
    out[:, 1, 2] = K[:, 1, 2] + corrections[:, 3] * height
    return out
