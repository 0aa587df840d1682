"""The full model: DepthNet (with or without the latent bank) and the VAE-constrained PoseNet.

Pose direction (as Monodepth2): the pose network always reads a pair in temporal order, earlier frame as
``target`` and later frame as ``source``, so what it predicts is the motion forward in time,
``T_later_earlier`` (maps points in the earlier camera frame into the later one). For the next frame that
is directly ``T_next_cur``; for the previous frame it predicts ``T_cur_prev`` and the warp uses its inverse
``T_prev_cur``. Both predicted vectors are forward motions, so one prior (N(0, I)) fits both.

In training mode with ``pose_vae`` (and ``pose_sample``) the vector driving the warp is the reparameterised
sample ``mean + exp(logvar / 2) * eps``; in eval mode, without ``pose_vae`` and with ``pose_sample`` false it is
the mean (the log-variance is still predicted, so the KL still applies).

Intrinsics: samples whose K is unknown use the learned K of their dataset's camera (:mod:`endoflow.models.intrinsics`,
:meth:`EndoflowModel.camera_K`).

Depth: disparity ``sigma`` in (0, 1) maps linearly to inverse depth between ``1 / max_depth`` and
``1 / min_depth`` (Monodepth2's ``disp_to_depth``), so depth lies in ``[min_depth, max_depth]`` cm.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from endoflow.config import DATASETS, ModelConfig, Params
from endoflow.errors import DataFormatError
from endoflow.geometry.pose import invert_pose, pose_vec_to_matrix
from endoflow.models.depth_net import DepthNet
from endoflow.models.intrinsics import CameraIntrinsics
from endoflow.models.latent_bank import GeneratorSpec, LatentBankGenerator, load_generator
from endoflow.models.model_file import ModelRecord, load_model_file
from endoflow.models.pose_net import PoseNet


@dataclass
class PoseEstimate:
    """One source frame's pose for the warp.

    Attributes:
        T_source_target: ``[B, 4, 4]`` what the warp uses (maps target-frame points into the source frame).
        vec: ``[B, 6]`` the forward-in-time motion vector behind it (sample in training, else the mean).
        mean, logvar: ``[B, 6]`` the predicted Gaussian over ``vec`` (``logvar`` ``None`` without pose_vae).
        source_is_next: whether the source is the next frame (``T_source_target`` is ``vec``'s motion) or the
            previous one (its inverse).
    """

    T_source_target: torch.Tensor
    vec: torch.Tensor
    mean: torch.Tensor
    logvar: torch.Tensor | None
    source_is_next: bool

    def spread_and_mean_parts(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``T_source_target`` twice, equal to it to the bit: the first back-propagates into the sample's spread
        alone (the mean's two paths cancel), the second into the mean alone (the sample's noise detached). Without
        sampling the first is constant."""
        no_mean = self.vec + (self.mean.detach() - self.mean)
        mean_only = self.vec.detach() + (self.mean - self.mean.detach())
        return source_transform(no_mean, self.source_is_next), source_transform(mean_only, self.source_is_next)


def source_transform(vec: torch.Tensor, source_is_next: bool) -> torch.Tensor:
    """``T_source_target [B, 4, 4]`` of the forward motion ``vec [B, 6]`` (``T_later_earlier``): itself for the next
    frame, its inverse for the previous one."""
    T_later_earlier = pose_vec_to_matrix(vec)
    return T_later_earlier if source_is_next else invert_pose(T_later_earlier)


class EndoflowModel(nn.Module):
    def __init__(self, model_cfg: ModelConfig, generator: LatentBankGenerator | None) -> None:
        super().__init__()
        self.cfg = model_cfg
        self.depth_net = DepthNet(model_cfg, generator)
        self.pose_net = PoseNet(model_cfg.pose_vae, model_cfg.encoder_weights, model_cfg.pose_logvar_init)
        self.intrinsics = CameraIntrinsics(len(DATASETS))

    def camera_K(self, batch: dict) -> torch.Tensor:
        """``K [B, 3, 3]`` float32 of a loader batch: its own where known, else its camera's learned one."""
        if "camera" not in batch:  # frames without the shards' camera fields: K as given
            return batch["K"].float()
        return self.intrinsics(batch["K"], batch["camera"], batch["intrinsics_known"], tuple(batch["cur"].shape[-2:]))

    def learned_K(self, dataset: str, K_assumed: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        """``[3, 3]``: the learned K of ``dataset``'s camera from its assumed ``K_assumed`` at ``size``."""
        camera = torch.tensor([DATASETS.index(dataset)], device=K_assumed.device)
        return self.intrinsics.corrected(K_assumed.float()[None], camera, size)[0]

    def disp_to_depth(self, disp: torch.Tensor) -> torch.Tensor:
        """Sigmoid disparity (any shape) -> z-depth in cm within ``[min_depth, max_depth]``, in float32 whatever
        the network's precision (depth feeds the geometry, which stays float32)."""
        min_disp, max_disp = 1.0 / self.cfg.max_depth, 1.0 / self.cfg.min_depth
        return 1.0 / (min_disp + (max_disp - min_disp) * disp.float())

    def predict_depth(self, rgb: torch.Tensor) -> torch.Tensor:
        """Full-resolution z-depth ``[B, 1, H, W]`` in cm of RGB ``[B, 3, H, W]`` in [0, 1]."""
        return self.disp_to_depth(self.depth_net(rgb)[0])

    def forward_motion(
        self, earlier: torch.Tensor, later: torch.Tensor, sample: bool
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """(vector used, mean, logvar) of ``T_later_earlier``; the vector is a sample when ``sample`` and the
        network predicts a variance, else the mean. All three are float32 whatever the network's precision:
        the vector becomes a pose matrix for the geometry, and the KL of a bf16 log-variance would round."""
        mean, logvar = self.pose_net(earlier, later)
        mean, logvar = mean.float(), (logvar.float() if logvar is not None else None)
        if sample and logvar is not None:
            vec = mean + torch.exp(0.5 * logvar) * torch.randn_like(mean)
        else:
            vec = mean
        return vec, mean, logvar

    def source_pose(self, target: torch.Tensor, source: torch.Tensor, source_is_next: bool) -> PoseEstimate:
        """The pose that warps ``source`` (the next or the previous frame) into ``target``; sampled in
        training mode unless ``pose_sample`` is off."""
        return self._pose_of_source(target, source, source_is_next, sample=self.training and self.cfg.pose_sample)

    @torch.no_grad()
    def predict_pose(self, target: torch.Tensor, source: torch.Tensor, source_is_next: bool = True) -> torch.Tensor:
        """Mean ``T_source_target [B, 4, 4]``; ``source`` is the next frame unless ``source_is_next=False``."""
        return self._pose_of_source(target, source, source_is_next, sample=False).T_source_target

    def _pose_of_source(
        self, target: torch.Tensor, source: torch.Tensor, source_is_next: bool, sample: bool
    ) -> PoseEstimate:
        """The one place of the earlier/later rule (module docstring): the network reads the pair in temporal
        order, and its forward motion is ``T_source_target`` for the next frame, the inverse for the previous."""
        earlier, later = (target, source) if source_is_next else (source, target)
        vec, mean, logvar = self.forward_motion(earlier, later, sample)
        return PoseEstimate(T_source_target=source_transform(vec, source_is_next), vec=vec, mean=mean, logvar=logvar,
                            source_is_next=source_is_next)


def generator_spec(params: Params) -> GeneratorSpec:
    """The generator architecture that ``params.latent_bank`` describes."""
    cfg = params.latent_bank
    return GeneratorSpec(
        resolution=cfg.resolution,
        start_resolution=cfg.start_resolution,
        latent_dim=cfg.latent_dim,
        style_dim=cfg.style_dim,
        mapping_layers=cfg.mapping_layers,
        channel_base=cfg.channel_base,
        channel_max=cfg.channel_max,
        conv_init_scale=cfg.conv_init_scale,
    )


def build_model(params: Params, latent_bank_path: str | None) -> EndoflowModel:
    """The model ``params.model`` describes.

    With ``model.latent_bank`` the generator is loaded from ``latent_bank_path`` (its architecture comes
    from the file) and frozen; ``latent_bank_path=None`` gives a randomly initialised, frozen bank of the
    ``params.latent_bank`` architecture (for summaries and tests; training passes the pretrained file).
    """
    generator = None
    if params.model.latent_bank:
        generator = load_generator(latent_bank_path) if latent_bank_path else LatentBankGenerator(generator_spec(params))
    return EndoflowModel(params.model, generator)


def load_trained_model(path: str | Path, device: torch.device) -> tuple[EndoflowModel, ModelRecord]:
    """The trained model in eval mode on ``device``, rebuilt from the params stored with it in its model file."""
    record = load_model_file(path)
    # the bank's weights are part of the state dict: build an empty one, then load everything
    model = build_model(record.params, latent_bank_path=None)
    state = dict(record.state)
    # model files from before learned intrinsics: every camera as assumed
    state.setdefault("intrinsics.corrections", model.intrinsics.corrections.detach().clone())
    try:
        model.load_state_dict(state)
    except RuntimeError as exc:  # missing, unexpected or misshapen tensors
        raise DataFormatError(path, f"weights do not fit the architecture of its params "
                                    f"({' '.join(str(exc).split())[:300]})") from None
    return model.to(device).eval(), record
