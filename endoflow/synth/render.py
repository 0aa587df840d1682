"""Render one frame of a tube scene: RGB lit by a light at the camera, and exact z-depth at pixel centres.

RGB is supersampled; depth is taken where the readers' K puts the pixel centres (integer coordinates). The
shading model: docs/synthetic_data.md, "Camera, light and mucosa".
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from endoflow.synth.texture import GAMMA
from endoflow.synth.tube import SurfacePoints, Tube, intersect, surface_points, tube_view

MAX_DEPTH_CM = 20.0
DEPTH_MARGIN_CM = 0.3
ATLAS_PAD = 2
DIFFUSE_POWER = 0.6  # softened Lambert: mucosa scatters light under its surface
LIGHT_RADIUS_CM = 0.5  # radius of the LED ring around the lens  # wrapped columns on each side of the atlas, so bilinear lookups wrap around


@dataclass
class LightStyle:
    exposure: float  # scales radiance before the display curve (a wall at 1 cm facing the camera ~ 1)
    diffuse: float
    specular: float
    shininess: float
    vignetting: float  # exponent p of the cos^p fall-off towards the image corners
    ambient: float


@dataclass
class TubeScene:
    """Everything needed to render frames of one sequence (built once, reused for every frame)."""

    tube: Tube
    atlas: torch.Tensor  # [1, 5, rows, width + 2 * ATLAS_PAD] albedo (3), bump slopes (2); wrapped borders
    texel_cm: float  # arc length per atlas row
    light: LightStyle


def make_scene(tube: Tube, atlas: np.ndarray, texel_cm: float, light: LightStyle, device: torch.device) -> TubeScene:
    """Upload the atlas (``[rows, width, 5]``: linear albedo, bump slopes along and around) with wrapped
    borders for periodic lookups."""
    padded = np.concatenate([atlas[:, -ATLAS_PAD:], atlas, atlas[:, :ATLAS_PAD]], axis=1)
    tensor = torch.as_tensor(np.ascontiguousarray(padded.transpose(2, 0, 1)), device=device)[None]
    return TubeScene(tube=tube, atlas=tensor, texel_cm=texel_cm, light=light)


def cap_joint(tube: Tube, origin: np.ndarray, first: int) -> int:
    """The farthest joint plane that can close the tube with every visible point under 20 cm away.

    A point of slab ``i`` is at most ``|c_i - o| + L_i + max radius`` from the camera; z-depth is at
    most that distance.
    """
    reach = np.linalg.norm(tube.joints[:-1] - origin, axis=1) + tube.lengths
    reach += np.maximum(tube.radii, tube.radii + tube.slopes * tube.lengths) + DEPTH_MARGIN_CM
    within = np.cumsum(reach[first:] > MAX_DEPTH_CM) == 0
    last = first + int(within.sum())  # slabs first .. last-1 are entirely within range
    if last <= first:
        raise ValueError("the camera is within 20 cm of nothing: tube too short or camera outside it")
    return last


def pixel_rays(K: np.ndarray, height: int, width: int, supersample: int, device: torch.device) -> torch.Tensor:
    """Camera-frame rays ``K^-1 [u, v, 1]`` (z = 1): ``[H*W*s*s + H*W, 3]``, sub-pixel samples then centres."""
    key = (np.asarray(K, dtype=np.float64).tobytes(), height, width, supersample, str(device))
    return _cached_pixel_rays(key)


@functools.lru_cache(maxsize=8)
def _cached_pixel_rays(key: tuple) -> torch.Tensor:
    K_bytes, height, width, supersample, device = key
    K = np.frombuffer(K_bytes, dtype=np.float64).reshape(3, 3).copy()
    offsets = (torch.arange(supersample, dtype=torch.float64) + 0.5) / supersample - 0.5
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij")
    sub_u = (u[:, :, None, None] + offsets[None, None, None, :]).expand(height, width, supersample, supersample)
    sub_v = (v[:, :, None, None] + offsets[None, None, :, None]).expand(height, width, supersample, supersample)
    uu = torch.cat([sub_u.reshape(-1), u.reshape(-1)])
    vv = torch.cat([sub_v.reshape(-1), v.reshape(-1)])
    pixels = torch.stack([uu, vv, torch.ones_like(uu)], dim=-1)
    rays = pixels @ torch.linalg.inv(torch.as_tensor(K, dtype=torch.float64)).T
    return rays.to(device=device, dtype=torch.float32)


def render_tube_frame(
    scene: TubeScene, pose: np.ndarray, K: np.ndarray, height: int, width: int, supersample: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """RGB ``[H, W, 3]`` float32 in [0, 1] and z-depth ``[H, W]`` float32 cm for camera-to-world ``pose``.

    ``K`` is the 3x3 pixel intrinsics at ``height x width`` (pixel centres at integer coordinates).
    """
    if pose.shape != (4, 4) or K.shape != (3, 3):
        raise ValueError(f"pose must be 4x4 and K 3x3, got {pose.shape} and {K.shape}")
    device = scene.atlas.device
    origin = pose[:3, 3]
    first = max(scene.tube.slab_containing(origin) - 1, 0)
    view = tube_view(scene.tube, origin, first, cap_joint(scene.tube, origin, first), device)
    camera_rays = pixel_rays(K, height, width, supersample, device)
    rays = camera_rays @ torch.as_tensor(pose[:3, :3].T, dtype=torch.float32, device=device)
    hits = intersect(view, rays)
    surface = surface_points(view, rays, hits)
    colour = _shade(scene, rays, camera_rays, hits.t, surface)

    samples = height * width * supersample * supersample
    rgb = colour[:samples].reshape(height, width, supersample * supersample, 3).mean(dim=2)
    depth = hits.t[samples:].reshape(height, width)
    return rgb.cpu().numpy(), depth.cpu().numpy()


def _shade(
    scene: TubeScene, rays: torch.Tensor, camera_rays: torch.Tensor, t: torch.Tensor, surface: SurfacePoints
) -> torch.Tensor:
    light = scene.light
    ray_length = rays.norm(dim=-1)
    distance = t * ray_length
    texel = _sample_atlas(scene, surface.arc, surface.angle)
    albedo = texel[:, :3]
    normals = _bumped_normals(surface, texel[:, 3:])
    facing = (-(normals * rays).sum(-1) / ray_length).clamp(0, 1)
    irradiance = 1.0 / (distance.square() + LIGHT_RADIUS_CM**2)
    # Mucosa scatters light under its surface: a softened cosine keeps grazing walls from going black.
    diffuse = albedo * (light.diffuse * facing.pow(DIFFUSE_POWER) * irradiance + light.ambient)[:, None]
    highlight = (light.specular * facing.pow(light.shininess) * irradiance)[:, None]
    # cos of the angle off the optical axis is 1 / |K^-1 [u, v, 1]|.
    vignette = camera_rays.norm(dim=-1).pow(-light.vignetting)[:, None]
    radiance = light.exposure * (diffuse + highlight) * vignette
    # Clipped per channel, as a camera does: near walls saturate in red first and turn orange-yellow.
    return radiance.clamp(0, 1).pow(1 / GAMMA)


def _bumped_normals(surface: SurfacePoints, slopes: torch.Tensor) -> torch.Tensor:
    """Shading normals tilted by the bump slopes (geometry and depth stay those of the smooth wall)."""
    bumped = surface.shading_normals - slopes[:, :1] * surface.along - slopes[:, 1:] * surface.around
    return bumped / bumped.norm(dim=-1, keepdim=True)


def _sample_atlas(scene: TubeScene, arc: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Bilinear atlas values ``[N, C]`` at (arc length, angle); the angle wraps around."""
    _, _, rows, padded_width = scene.atlas.shape
    width = padded_width - 2 * ATLAS_PAD
    x = ATLAS_PAD + (angle + torch.pi) / (2 * torch.pi) * width
    y = arc / scene.texel_cm
    grid = torch.stack([2 * x / padded_width - 1, 2 * y / rows - 1], dim=-1)
    sampled = F.grid_sample(scene.atlas, grid[None, None], mode="bilinear", padding_mode="border", align_corners=False)
    return sampled[0, :, 0].T
