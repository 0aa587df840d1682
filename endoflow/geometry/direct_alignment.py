"""Direct photometric alignment of a frame to a keyframe with known depth (the tracking of DSO and of
Endo-Depth-and-Motion, reduced to one keyframe): the rigid motion and an affine brightness change that make the
frame, warped into the keyframe with the keyframe's depth, look like the keyframe, with a prior that holds the
rotation near the start's (the tracker starts each frame from the previous frame's pose and the pose network's
step, so the prior holds the rotation of each step near the network's).

Residual per keyframe pixel and colour channel: ``r = exp(a) * I_frame(w(p)) + b - I_key(p)``, where ``w`` moves
the keyframe point at ``p`` (its depth ``d``) into the frame by ``T_frame_key`` and projects it. Gauss-Newton with
Levenberg-Marquardt damping on the 8 parameters (a left increment ``(omega, t)`` of the pose, gain ``a``, offset
``b``), Huber weights, coarse to fine over an image pyramid; the pixels in float32, the parameters in float64. The
light sits at the lens, so a point seen from further away is darker: the frame's brightness is brought to the
keyframe's distance (``light_falloff``). Pixels take part where the keyframe has depth, lands inside the frame in
front of its camera, and is, in both images, neither saturated (a specular highlight, which moves with the light)
nor black (the dark border of an endoscope's field of view). The prior adds ``rotation_prior / 2 * |theta|^2`` to
each pixel's cost, ``theta`` the axis-angle of the rotation between the current pose and the start: with a model's
depth, which is wrong in shape away from its training data, the photometric cost trades rotation against
translation, and the pose network's rotation keeps the two apart. A step is kept only where it lowers the cost
over the pixels that take part both before and after it (and keeps at least half of them), so the result is
never worse than the start. On a CPU the costs and the normal equations' rows are compiled loops
(``alignment_loops.py``), the same figures to float32 rounding. See docs/reconstruction.md, "The path refined".
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F

from endoflow.config import RefineConfig
from endoflow.geometry import alignment_loops
from endoflow.geometry.camera import backproject, intrinsics_inverse, scale_intrinsics
from endoflow.geometry.depth_scale import depth_scale_to_keyframe
from endoflow.geometry.warp import sampling_grid
from endoflow.geometry.pose import invert_pose, nearest_rigid, pose_vec_to_matrix
from endoflow.shapes import check_shape

SATURATED = 0.98  # a keyframe pixel with a channel above this is a highlight
BLACK = 0.02  # a keyframe pixel with every channel below this is outside the field of view
KEPT_SHARE = 0.5  # a step that leaves fewer than this share of the pixels taking part is refused
# A level ends once the step it would try next moves the pose by less than this (radians, or the depth's unit: cm):
# at the cost's noise floor Levenberg-Marquardt refuses step after step, each a quarter of the last, down to 1e-9.
# Against 1e-7 (the accepted step's old threshold), 1e-5 took the cost evaluations of a tracked frame of exact depth
# from 56.4 to 30.2 at 480 px (half the pixels evaluated) and from 52.2 to 36.0 at 64 px, and left the errors of 12
# tracked frames against the truth the same to 4 digits at 64, 256 and 480 px (the steps moved by at most 2.3e-4
# deg); 1e-4 moved them (docs/benchmarks.md, "The refinement's levels end at the noise floor").
MIN_STEP = 1e-5
# On a GPU the dampings a step would try one after the other are tried this many at a time: one more costs little
# there, and each wait for the device costs much (with the untrained model's depth at 480 px a step tried 1.6
# candidates on average). A CPU tries one at a time: there every candidate costs its full share.
CANDIDATES_AT_ONCE = 3
REFINE = RefineConfig()  # the defaults' one source, the config schema
# The pixels' arithmetic (images, points, residuals, Jacobians, the normal equations' sums); the pose, the brightness
# and each step are solved and composed in float64. Against all-float64, float32 moved the steps of 12 tracked frames
# by at most 7e-5 of their length and 2e-4 deg, and the test sets' refined paths by at most 0.0009 cm ATE, at 480 px
# in 0.65 of the time (docs/reconstruction.md, "The path refined").
PIXEL_DTYPE = torch.float32


@dataclass(frozen=True)
class AlignmentSettings:
    """How one frame is aligned (``refine.*``, see the config schema): pyramid levels and the finest one's size at
    most, Gauss-Newton steps per level, the Huber threshold, the light's fall-off and the rotation prior's weight."""

    levels: int = REFINE.levels
    max_size: int | None = REFINE.max_size
    iterations: int = REFINE.iterations
    huber: float = REFINE.huber
    min_pixels: int = 64  # fewer valid pixels at a level: that level is skipped
    light_falloff: float = REFINE.light_falloff
    rotation_prior: float = REFINE.rotation_prior
    # on a CPU the costs and normal equations as compiled loops (alignment_loops.py); False: the tensor code, as on
    # a GPU
    compiled: bool = True


@dataclass(frozen=True)
class Alignment:
    """The result: ``T_frame_key [4, 4]`` (float64, on the CPU), the brightness ``gain``/``offset``, the robust
    cost at the start and at the end (finest level, same pixels), and the share of keyframe pixels that took part."""

    T_frame_key: torch.Tensor
    gain: float
    offset: float
    cost_start: float
    cost_end: float
    valid_share: float


def align_to_keyframe(key_rgb: torch.Tensor, key_depth: torch.Tensor, frame_rgb: torch.Tensor, K: torch.Tensor,
                      T_frame_key: torch.Tensor, settings: AlignmentSettings = AlignmentSettings()) -> Alignment:
    """Refine ``T_frame_key`` (maps keyframe-camera points into the frame's camera) from its start value.

    Args:
        key_rgb, frame_rgb: ``[3, H, W]`` images in [0, 1].
        key_depth: ``[1, H, W]`` z-depth of the keyframe (0: unknown), the unit of the translation.
        K: ``[3, 3]`` pixel intrinsics of both images.
        T_frame_key: ``[4, 4]`` start.

    The pixels' work runs on the images' device (``K`` joins them there); the 8 parameters, each step's solve and
    the decisions stay on the CPU, so a GPU is waited for about three times a Gauss-Newton step (the pixels taking
    part, the normal equations, each candidate's costs), not at every small operation. The result is on the CPU.
    """
    sizes = check_shape("key_rgb", key_rgb, "3,H,W")
    check_shape("frame_rgb", frame_rgb, "3,H,W", **sizes)
    check_shape("key_depth", key_depth, "1,H,W", **sizes)
    check_shape("K", K, "3,3")
    check_shape("T_frame_key", T_frame_key, "4,4")
    device = key_rgb.device
    key_rgb, key_depth, frame_rgb, K = (tensor.detach() for tensor in (key_rgb, key_depth, frame_rgb, K))
    pyramid = _pyramid(key_rgb.to(PIXEL_DTYPE), key_depth.to(device, PIXEL_DTYPE), frame_rgb.to(device, PIXEL_DTYPE),
                       K.to(device, PIXEL_DTYPE), settings.levels, settings.max_size,
                       compiled=settings.compiled and device.type == "cpu")
    pose = T_frame_key.detach().to("cpu", torch.float64).clone()
    brightness = torch.zeros(2, dtype=torch.float64)
    start, start_brightness = pose.clone(), brightness.clone()
    prior = _RotationPrior(start[:3, :3], settings.rotation_prior)
    for level in reversed(pyramid):
        pose, brightness = _refine_level(level, pose, brightness, settings, prior)
    finest = pyramid[0]
    (cost_start, cost_end, both), = _compare(_costs(finest, start[None], start_brightness[None], settings, prior),
                                             _costs(finest, pose[None], brightness[None], settings, prior))
    if not cost_end <= cost_start:  # coarse levels can mislead: never hand back worse than the start
        pose, brightness, cost_end = start, start_brightness, cost_start
    return Alignment(pose, float(torch.exp(brightness[0])), float(brightness[1]), cost_start, cost_end,
                     both / max(1, int(finest.usable.sum())))


@dataclass(frozen=True)
class _RotationPrior:
    """The rotation's pull towards ``start [3, 3]`` with weight ``weight`` (see the module docstring)."""

    start: torch.Tensor
    weight: float

    def departure(self, pose: torch.Tensor) -> torch.Tensor:
        """``[3]`` axis-angle (radians) of ``pose``'s rotation after the start's: ``R_pose = exp(theta) R_start``,
        the left increment the Gauss-Newton steps use. In closed form: this runs at every candidate step."""
        R = pose[:3, :3] @ self.start.T
        sine_axis = torch.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2
        sine = sine_axis.norm()
        angle = torch.atan2(sine, (R.trace() - 1) / 2)
        return sine_axis * (angle / sine) if float(sine) > 1e-12 else sine_axis

    def cost(self, pose: torch.Tensor) -> float:
        """The prior's share of each pixel's cost at ``pose``."""
        return 0.5 * self.weight * float(self.departure(pose).square().sum()) if self.weight else 0.0

    def normal_equations(self, pose: torch.Tensor, pixels: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The prior's terms ``[6, 6]``, ``[6]`` of the Gauss-Newton system in the pose's left increment
        ``(omega, t)`` over ``pixels`` pixels: its residual ``sqrt(weight) * theta`` once per pixel, with
        ``d theta / d omega`` taken as the identity (exact at the start, where the steps begin)."""
        hessian = torch.zeros(6, 6, dtype=pose.dtype, device=pose.device)
        gradient = torch.zeros(6, dtype=pose.dtype, device=pose.device)
        hessian[:3, :3] = self.weight * pixels * torch.eye(3, dtype=pose.dtype, device=pose.device)
        gradient[:3] = self.weight * pixels * self.departure(pose)
        return hessian, gradient


@dataclass(frozen=True)
class _Level:
    key_rgb: torch.Tensor  # [3, H, W]
    points: torch.Tensor  # [3, N] keyframe-camera points of the pixels with depth
    key_values: torch.Tensor  # [3, N] their colours
    usable: torch.Tensor  # [N] bool: with depth, neither saturated nor black
    frame: torch.Tensor  # [1, 4, H, W] the frame and where it is well exposed
    gradients: torch.Tensor  # [1, 6, H, W] its horizontal and vertical gradients (only a step needs them)
    K: torch.Tensor
    compiled: bool = False  # its costs and normal equations computed by alignment_loops (on a CPU)

    @cached_property
    def distance(self) -> torch.Tensor:
        """``[N]`` the points' distance from the keyframe's camera (its light): only a light fall-off needs it."""
        return self.points.norm(dim=0).clamp(min=1e-9)

    def loop_arrays(self, falloff: float) -> alignment_loops.LevelArrays:
        """What :mod:`alignment_loops` reads of the level, as arrays sharing the tensors' memory (the distances
        empty without a light fall-off, which alone reads them)."""
        distance = self.distance if falloff else self.points.new_empty(0)
        return alignment_loops.LevelArrays(self.points.numpy(), self.key_values.numpy(), self.usable.numpy(),
                                           self.frame[0].numpy(), self.gradients[0].numpy(), self.K.numpy(),
                                           distance.numpy(), self._rows)

    @cached_property
    def _rows(self) -> np.ndarray:
        """The room the compiled loops write a step's Jacobian into (three rows of 9 for each usable point: up to 25
        MB at 480 px), made once per level rather than at each step."""
        return np.empty((3 * int(self.usable.sum()), alignment_loops.JACOBIAN_ROWS + 1), np.float32)


def halvings_to_fit(height: int, width: int, max_size: int | None) -> int:
    """How many times a ``height x width`` image is halved for its longer side to be at most ``max_size`` (None:
    never), its shorter side kept at 4 px at least."""
    halvings = 0  # each halving rounds down, as average pooling does
    while max_size is not None and max(height, width) >> halvings > max_size and min(height, width) >> halvings >= 8:
        halvings += 1
    return halvings


def _pyramid(key_rgb: torch.Tensor, key_depth: torch.Tensor, frame_rgb: torch.Tensor, K: torch.Tensor,
             levels: int, max_size: int | None = None, compiled: bool = False) -> list[_Level]:
    """``levels`` levels, finest first, the finest halved from the images until it fits ``max_size``; ``compiled``:
    their per-pixel work as compiled loops (the images on the CPU)."""
    pyramid = []
    # well exposed at full resolution: a coarse pixel is only if all four below it are (a coarse pixel at the
    # field of view's edge averages black in, and is no image of the scene)
    key_good, frame_good = (_well_exposed(image)[None].to(image.dtype) for image in (key_rgb, frame_rgb))
    skipped = halvings_to_fit(*key_rgb.shape[-2:], max_size)
    for level in range(skipped + max(1, levels)):
        if level:
            key_rgb, frame_rgb = F.avg_pool2d(key_rgb, 2), F.avg_pool2d(frame_rgb, 2)
            key_good, frame_good = (F.avg_pool2d(good, 2).eq(1).to(good.dtype) for good in (key_good, frame_good))
            # average depth only over pixels that have it
            known = F.avg_pool2d((key_depth > 0).to(key_depth.dtype), 2)
            key_depth = F.avg_pool2d(key_depth, 2) / known.clamp(min=1e-9) * (known > 0.99)
            K = scale_intrinsics(K, 0.5, 0.5)
        if min(key_rgb.shape[-2:]) < 4:
            break
        if level < skipped:
            continue
        points = backproject(key_depth[None], intrinsics_inverse(K)[None])[0]
        usable = (key_good.reshape(-1) > 0) & (key_depth.reshape(-1) > 0)
        gx = F.pad(frame_rgb[:, :, 2:] - frame_rgb[:, :, :-2], (1, 1, 0, 0)) / 2
        gy = F.pad(frame_rgb[:, 2:, :] - frame_rgb[:, :-2, :], (0, 0, 1, 1)) / 2
        frame, gradients = torch.cat([frame_rgb, frame_good])[None], torch.cat([gx, gy])[None]
        pyramid.append(_Level(key_rgb, points, key_rgb.reshape(3, -1), usable, frame, gradients, K, compiled))
    return pyramid


def _well_exposed(rgb: torch.Tensor) -> torch.Tensor:
    """``[H, W]`` bool: neither saturated nor black. (Sampled bilinearly, a frame point takes part only where all
    four pixels around it are.)"""
    brightest = rgb.max(dim=0).values
    return (brightest < SATURATED) & (brightest > BLACK)


class _Sample(NamedTuple):
    """The frame at the keyframe points moved by each of ``B`` poses: its colours ``[B, 3, N]``, the moved points
    ``[B, 3, N]``, their pixels ``[B, 2, N]``, the sampling grid ``[1, B, N, 2]`` and which points take part ``[B,
    N]`` (land inside, one pixel from the border, in front, among well-exposed frame pixels)."""

    values: torch.Tensor
    moved: torch.Tensor
    pixels: torch.Tensor
    grid: torch.Tensor
    inside: torch.Tensor

    def pick(self, index: int) -> "_Sample":
        """The sample of pose ``index`` alone (``B`` = 1)."""
        return _Sample(self.values[index:index + 1], self.moved[index:index + 1], self.pixels[index:index + 1],
                       self.grid[:, index:index + 1], self.inside[index:index + 1])


class _States(NamedTuple):
    """What the compiled loops need to take a state up again: the states as :func:`_costs` packs them ``[B, 15]``
    (float32; they sample the frame themselves)."""

    packed: torch.Tensor

    def pick(self, index: int) -> "_States":
        """State ``index`` alone (``B`` = 1)."""
        return _States(self.packed[index:index + 1])


def _sample(level: _Level, rigid: torch.Tensor) -> _Sample:
    """The frame's colours at the keyframe points moved by each of ``rigid [B, 3, 4]`` (``[R | t]`` on the pixels'
    device; a cost needs no more; a step also samples the gradients there, :func:`_sampled_gradients`: most
    candidates are refused, so they are not sampled for nothing)."""
    moved = rigid[:, :, :3] @ level.points + rigid[:, :, 3:]
    z = moved[:, 2]
    projected = level.K @ moved
    u, v = projected[:, 0] / z.clamp(min=1e-9), projected[:, 1] / z.clamp(min=1e-9)
    height, width = level.frame.shape[-2:]
    inside = (z > 1e-6) & (u >= 1) & (u <= width - 2) & (v >= 1) & (v <= height - 2)
    grid = sampling_grid(u, v, height, width)[None]
    sampled = _grid_sample(level.frame, grid)
    return _Sample(sampled[:3].transpose(0, 1), moved, torch.stack([u, v], dim=1), grid,
                   inside & (sampled[3] > float(alignment_loops.WELL_EXPOSED)))


def _sampled_gradients(level: _Level, sample: _Sample, points: torch.Tensor) -> torch.Tensor:
    """``[6, M]``: the frame's horizontal and vertical gradients where ``sample`` sampled the colours of ``points``
    (indices ``[M]`` into its points; each point is sampled on its own, so a subset samples as the whole would)."""
    return _grid_sample(level.gradients, sample.grid.index_select(2, points))[:, 0]


def _grid_sample(image: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """``image [1, C, H, W]`` sampled bilinearly at ``grid [1, B, N, 2]``: ``[C, B, N]`` (each channel and point on
    its own, so sampling channels or points apart gives what sampling them together does, to the bit)."""
    return F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=True)[0]


def _huber(residual: torch.Tensor, delta: float) -> torch.Tensor:
    """``0.5 r^2`` up to ``|r| = delta``, ``delta (|r| - delta / 2)`` beyond: both as ``m (|r| - m / 2)`` with ``m =
    min(|r|, delta)``, the same to the bit (halving is exact) in fewer passes over the pixels."""
    absolute = residual.abs()
    least = absolute.clamp(max=delta)
    return least * (absolute - 0.5 * least)


def _lit(level: _Level, moved: torch.Tensor, falloff: float) -> torch.Tensor | float:
    """``[..., 1, N]`` factor that brings a frame pixel's brightness to the keyframe's light, for points ``moved [...,
    3, N]``: (distance in the frame / distance in the keyframe) ^ falloff; 1 without a fall-off (the default), where
    the distances, the dearest part of a cost at 480 px, would only be raised to the power 0."""
    if not falloff:
        return 1.0
    return (moved.norm(dim=-2, keepdim=True).clamp(min=1e-9) / level.distance) ** falloff


def _costs(level: _Level, poses: torch.Tensor, brightness: torch.Tensor, settings: AlignmentSettings,
           prior: _RotationPrior) -> tuple[torch.Tensor, torch.Tensor, _Sample | _States]:
    """Per-pixel costs ``[B, N]`` (Huber, summed over channels, plus the rotation prior's share) at each of ``B``
    states (``poses [B, 4, 4]`` and ``brightness [B, 2]``, float64 on the CPU), where the pixels take part ``[B,
    N]``, and what a step from one linearises: the frame sampled at the poses, or for the compiled loops the
    states."""
    prior_costs = torch.tensor([prior.cost(pose) for pose in poses], dtype=poses.dtype)
    # each state as [R | t], gain, offset and prior cost, sent to the pixels' device in one copy that does not wait
    # for the device (from pageable memory the bytes are staged at once)
    packed = torch.cat([poses[:, :3].reshape(len(poses), 12), brightness[:, :1].exp(), brightness[:, 1:],
                        prior_costs[:, None]], dim=1).to(level.points.dtype).to(level.points.device, non_blocking=True)
    if level.compiled:
        costs, part = alignment_loops.state_costs(level.loop_arrays(settings.light_falloff), packed.numpy(),
                                                  settings.huber, settings.light_falloff)
        return torch.from_numpy(costs), torch.from_numpy(part), _States(packed)
    sample = _sample(level, packed[:, :12].reshape(-1, 3, 4))
    gain, offset, prior_cost = packed[:, 12:13, None], packed[:, 13:14, None], packed[:, 14:15]
    residual = gain * _lit(level, sample.moved, settings.light_falloff) * sample.values + offset - level.key_values
    return _huber(residual, settings.huber).sum(dim=1) + prior_cost, level.usable & sample.inside, sample


def _pick(costs: tuple[torch.Tensor, torch.Tensor, _Sample | _States], index: int
          ) -> tuple[torch.Tensor, torch.Tensor, _Sample | _States]:
    """State ``index`` alone of :func:`_costs`' result."""
    cost, part, sample = costs
    return cost[index:index + 1], part[index:index + 1], sample.pick(index)


def _compare(before: tuple[torch.Tensor, torch.Tensor, _Sample | _States],
             after: tuple[torch.Tensor, torch.Tensor, _Sample | _States]) -> list[tuple[float, float, int]]:
    """For each state of ``after`` (:func:`_costs`), the mean costs before (one state) and after over the pixels
    taking part in both, and how many those are: sums in float64 on the pixels' device, read back at once. A state
    that keeps fewer than :data:`KEPT_SHARE` of the pixels taking part before costs infinity."""
    (cost_before, part_before, _), (cost_after, part_after, _) = before, after
    both = part_before & part_after
    sums = [part_before, both] + [torch.where(mask, cost, 0) for mask, cost in
                                  ((part_before, cost_before), (both, cost_before), (both, cost_after))]
    judged = []
    for taking_part, in_both, before_all, before_both, after_both in torch.stack(
            [values.sum(dim=1, dtype=torch.float64).expand(len(both)) for values in sums], dim=1).tolist():
        if not in_both or in_both < KEPT_SHARE * taking_part:
            judged.append((before_all / taking_part if taking_part else 0.0, float("inf"), int(in_both)))
        else:
            judged.append((before_both / in_both, after_both / in_both, int(in_both)))
    return judged


def candidates_at_once(device: torch.device) -> int:
    """How many dampings a Gauss-Newton step tries at a time on ``device`` (:data:`CANDIDATES_AT_ONCE`)."""
    return 1 if device.type == "cpu" else CANDIDATES_AT_ONCE


def _refine_level(level: _Level, pose: torch.Tensor, brightness: torch.Tensor, settings: AlignmentSettings,
                  prior: _RotationPrior) -> tuple[torch.Tensor, torch.Tensor]:
    damping = 1e-3
    at_once = candidates_at_once(level.points.device)
    current = _costs(level, pose[None], brightness[None], settings, prior)  # then the accepted candidate's
    for _ in range(settings.iterations):
        normal, taking_part = _normal_equations(level, current[2], brightness, settings)
        if taking_part < settings.min_pixels:
            break
        hessian, gradient = normal[:, :8], normal[:, 8]
        if prior.weight:
            prior_hessian, prior_gradient = prior.normal_equations(pose, taking_part)
            hessian[:6, :6] += prior_hessian
            gradient[:6] += prior_gradient
        step = None  # the accepted one
        while damping < 1e6 and step is None:
            # the next dampings Levenberg-Marquardt would try one after the other; the first that lowers the cost wins
            dampings = [damping * 4 ** k for k in range(at_once) if damping * 4 ** k < 1e6]
            steps = [-torch.linalg.solve(hessian + tried * torch.diag(hessian.diagonal().clamp(min=1e-12)), gradient)
                     for tried in dampings]
            # one at a time, the first step below the floor ends the level: tried together, the steps before it
            kept = list(itertools.takewhile(lambda pair: float(pair[1][:6].abs().max()) >= MIN_STEP,
                                            zip(dampings, steps)))
            if not kept:
                return pose, brightness
            dampings, steps = [tried for tried, _ in kept], [step for _, step in kept]
            poses = torch.stack([pose_vec_to_matrix(tried[:6]) @ pose for tried in steps])
            brightnesses = torch.stack([brightness + tried[6:] for tried in steps])
            candidates = _costs(level, poses, brightnesses, settings, prior)
            damping = dampings[-1] * 4
            for index, (before, after, _) in enumerate(_compare(current, candidates)):
                if after < before:
                    pose, brightness, current = poses[index], brightnesses[index], _pick(candidates, index)
                    step, damping = steps[index], dampings[index] / 3
                    break
        if step is None:
            break
    return pose, brightness


def _normal_equations(level: _Level, at: _Sample | _States, brightness: torch.Tensor, settings: AlignmentSettings
                      ) -> tuple[torch.Tensor, int]:
    """The Gauss-Newton system at the state ``at`` (one, as :func:`_costs` left it) over the pixels taking part:
    ``[8, 9]`` float64 on the CPU, the Huber-weighted Hessian beside the gradient; and how many pixels took part."""
    if level.compiled:
        return alignment_loops.normal_equations(level.loop_arrays(settings.light_falloff), at.packed[0].numpy(),
                                                settings.huber, settings.light_falloff)
    points = (level.usable & at.inside[0]).nonzero()[:, 0]  # the pixels taking part
    system = _linearise(level, at, _sampled_gradients(level, at, points), brightness, points, settings.light_falloff)
    # Huber's weights, 1 up to the threshold and threshold / |r| beyond (huber / huber is exactly 1)
    weights = settings.huber / system[8].abs().clamp(min=settings.huber)
    # [8, 9]: the Hessian and the gradient in one product, read back in one transfer
    return ((system[:8] * weights) @ system.T).cpu().to(torch.float64), len(points)


def _linearise(level: _Level, sample: _Sample, gradients: torch.Tensor, brightness: torch.Tensor,
               points: torch.Tensor, falloff: float) -> torch.Tensor:
    """``[9, 3 M]``: the Jacobian's rows in (omega, t, gain, offset), then the residuals, over the three channels
    (channel-major) of the ``points [M]`` (indices) taking part, whose ``gradients [6, M]`` are sampled. A left
    increment moves a point ``X`` to ``X + omega x X + t``. Transposed, so that the normal equations are one
    product of long rows (a [3 M, 8] Jacobian cost a copy and two products)."""
    lit = _lit(level, sample.moved[0], falloff)
    gain = torch.exp(brightness[0]) * (lit.index_select(1, points) if falloff else lit)
    # what the step reads of each point taking part, gathered in one pass
    X, pixels, values, key_values = torch.cat([sample.moved[0], sample.pixels[0], sample.values[0],
                                               level.key_values]).index_select(1, points).split([3, 2, 3, 3])
    u, v = pixels
    K = level.K
    du = (K[0][:, None] - u * K[2][:, None]) / X[2]  # [3, M]: d u / d X
    dv = (K[1][:, None] - v * K[2][:, None]) / X[2]
    gx, gy = gradients[0:3], gradients[3:6]
    # d image / d X per coordinate and channel: [3 coordinates, 3 channels, M]; the light's factor grows with |X|
    d_image = gx[None] * du[:, None] + gy[None] * dv[:, None]
    if falloff:
        d_lit = falloff * X / X.square().sum(dim=0).clamp(min=1e-18)  # d log(lit) / d X
        d_image = d_image + values[None] * d_lit[:, None]
    d_image = gain * d_image
    # d X / d omega = -[X]_x, so d image / d omega = X x (d image / d X), written out (torch.cross of the [3, 3, M]
    # blocks cost as much as the rest of the Jacobian)
    x, y, z = X[:, None]
    d_x, d_y, d_z = d_image
    d_omega = [y * d_z - z * d_y, z * d_x - x * d_z, x * d_y - y * d_x]
    residual = gain * values + brightness[1] - key_values
    rows = [*d_omega, *d_image, gain * values, torch.ones_like(values), residual]
    return torch.stack(rows).reshape(9, -1)


@dataclass(frozen=True)
class TrackerSettings:
    """The alignment of each frame, and when a frame becomes the keyframe (``refine.keyframe_every``,
    ``refine.min_overlap``); the smoothing of the refined path's orientations (``refine.rotation_smoothing``), which
    the path's users apply to what the tracker returns (:mod:`endoflow.geometry.path_smoothing`): the tracker itself
    goes on from the poses as aligned; whether each frame's depth is rescaled to its keyframe's
    (``refine.depth_scale``, :mod:`endoflow.geometry.depth_scale`)."""

    alignment: AlignmentSettings = AlignmentSettings()
    keyframe_every: int = REFINE.keyframe_every
    min_overlap: float = REFINE.min_overlap
    rotation_smoothing: float = REFINE.rotation_smoothing
    depth_scale: bool = REFINE.depth_scale


def tracker_settings(cfg: RefineConfig) -> TrackerSettings:
    """The tracker's settings from the ``refine`` params."""
    alignment = AlignmentSettings(levels=cfg.levels, max_size=cfg.max_size, iterations=cfg.iterations, huber=cfg.huber,
                                  light_falloff=cfg.light_falloff, rotation_prior=cfg.rotation_prior)
    return TrackerSettings(alignment, keyframe_every=cfg.keyframe_every, min_overlap=cfg.min_overlap,
                           rotation_smoothing=cfg.rotation_smoothing, depth_scale=cfg.depth_scale)


class KeyframeTracker:
    """Camera-to-world poses of a frame sequence, each aligned to the current keyframe (the last frame made one)
    from a start the caller gives (the pose network's chain): :func:`align_to_keyframe`. Translations are in the
    keyframes' depth unit, so the path takes the depth's scale. With ``depth_scale`` each frame's depth is brought to
    its keyframe's once the frame is aligned (:func:`~endoflow.geometry.depth_scale.depth_scale_to_keyframe`; where
    too little of the keyframe lands on it, the last frame's factor), and a keyframe keeps its depth so rescaled: the
    whole sequence takes the first frame's scale. :attr:`depth_scale` is the factor on the last frame's depth, which
    the caller applies to what it fuses and writes (1 without the setting)."""

    def __init__(self, K: torch.Tensor, settings: TrackerSettings = TrackerSettings()) -> None:
        check_shape("K", K, "3,3")
        self.K = K.to(torch.float64)
        self.settings = settings
        self.keyframe: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None  # rgb, depth, T_world_key
        self.since_keyframe = 0
        self.keyframes = 0  # made so far
        self.last: Alignment | None = None
        self.depth_scale = 1.0

    def track(self, rgb: torch.Tensor, depth: torch.Tensor, T_world_start: torch.Tensor) -> torch.Tensor:
        """``T_world_frame [4, 4]`` (float64) of the next frame (``rgb [3, H, W]`` in [0, 1], its depth
        ``[1, H, W]``), refined from ``T_world_start`` (made rigid); the first frame keeps its start and becomes a
        keyframe. The pixels' work runs on the frame's device, the poses are kept and returned on the CPU."""
        check_shape("T_world_start", T_world_start, "4,4")
        start = nearest_rigid(T_world_start.detach().to("cpu", torch.float64))
        if self.keyframe is None:
            self.depth_scale = 1.0
            self._make_keyframe(rgb, depth, start)
            return start
        key_rgb, key_depth, T_world_key = self.keyframe
        T_frame_key = invert_pose(start) @ T_world_key
        self.last = align_to_keyframe(key_rgb, key_depth, rgb, self.K, T_frame_key, self.settings.alignment)
        # rigid at every frame: otherwise rounding, compounded through keyframes, shrinks the rotations to nothing
        T_world_frame = nearest_rigid(T_world_key @ invert_pose(self.last.T_frame_key))
        if self.settings.depth_scale:
            fitted = depth_scale_to_keyframe(key_depth, depth, self.K, self.last.T_frame_key)
            self.depth_scale = fitted if fitted is not None else self.depth_scale
        self.since_keyframe += 1
        if self.since_keyframe >= self.settings.keyframe_every or self.last.valid_share < self.settings.min_overlap:
            self._make_keyframe(rgb, depth * self.depth_scale, T_world_frame)
        return T_world_frame

    def _make_keyframe(self, rgb: torch.Tensor, depth: torch.Tensor, T_world_frame: torch.Tensor) -> None:
        self.keyframe = (rgb.to(PIXEL_DTYPE), depth.to(PIXEL_DTYPE), T_world_frame)
        self.since_keyframe = 0
        self.keyframes += 1
