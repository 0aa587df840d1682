"""Indoor box scenes for the SceneNet layout: a room with furniture-like blocks, seen by a moving camera.

Rays are cast exactly against axis-aligned boxes (slab method); world frame x, y horizontal, z up, cm. See
docs/synthetic_data.md, "Camera, light and mucosa" (SceneNet rooms).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

CLEARANCE_CM = 40.0  # no block comes closer than this to the camera path
SUN = (0.36, 0.48, 0.80)  # |component| of a fixed light direction along the normal of x, y, z faces


@dataclass
class Room:
    size: np.ndarray  # [3] room extent (the room spans [0, size])
    blocks: np.ndarray  # [M, 2, 3] lower and upper corners
    colours: np.ndarray  # [M + 6, 3] sRGB in [0, 1]: blocks, then the room's faces (-x, +x, -y, +y, floor, ceiling)


def make_room(rng: np.random.Generator, path: np.ndarray) -> Room:
    """A random room around a camera ``path`` ``[F, 3]`` (cm); blocks keep clear of the path."""
    size = path.max(axis=0) + rng.uniform(60, 160, size=3)
    size[2] = max(size[2], rng.uniform(240, 320))
    blocks = []
    for _ in range(200):
        if len(blocks) == 10:
            break
        footprint = rng.uniform(30, 200, size=2)
        height = rng.uniform(40, 220)
        corner = rng.uniform(0, 1, size=2) * (size[:2] - footprint)
        if rng.random() < 0.25:  # a shelf or cabinet hanging on a wall
            low = np.array([*corner, rng.uniform(90, 180)])
            block = np.stack([low, low + [*footprint, rng.uniform(20, 60)]])
        else:
            block = np.stack([[*corner, 0.0], [*(corner + footprint), height]])
        nearest = np.clip(path, block[0], block[1])
        if np.linalg.norm(nearest - path, axis=1).min() > CLEARANCE_CM:
            blocks.append(block)
    blocks_array = np.array(blocks).reshape(-1, 2, 3)
    colours = rng.uniform(0.2, 0.9, size=(len(blocks_array) + 6, 3))
    colours[-2] = rng.uniform(0.3, 0.6) * np.array([1.0, 0.8, 0.6])  # a wooden-ish floor
    return Room(size=size, blocks=blocks_array, colours=colours)


def camera_path(frames: int, rng: np.random.Generator) -> np.ndarray:
    """``[F, 4, 4]`` camera-to-world poses (OpenCV axes) wandering smoothly through a room-sized space."""
    f = np.arange(frames)[:, None]
    period = rng.uniform(12, 40, size=(1, 3))
    phase = rng.uniform(0, 2 * np.pi, size=(1, 3))
    centre = np.array([rng.uniform(150, 300), rng.uniform(150, 300), rng.uniform(120, 170)])
    amplitude = np.array([rng.uniform(40, 120), rng.uniform(40, 120), rng.uniform(5, 25)])
    position = centre + amplitude * np.sin(2 * np.pi * f / period + phase)
    turn = rng.uniform(0.15, 0.45) * rng.choice([-1.0, 1.0])  # radians per frame (frames are 25 apart)
    yaw = rng.uniform(0, 2 * np.pi) + turn * f[:, 0] + 0.4 * np.sin(f[:, 0] / 5.0)
    pitch = np.radians(rng.uniform(-25, 5) + 8 * np.sin(f[:, 0] / rng.uniform(4, 9)))
    forward = np.stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)], axis=1)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(forward, right)
    poses = np.tile(np.eye(4), (frames, 1, 1))
    poses[:, :3, :3] = np.stack([right, down, forward], axis=2)
    poses[:, :3, 3] = position
    return poses


def render_room(
    room: Room, pose: np.ndarray, K: np.ndarray, height: int, width: int, device: torch.device
) -> tuple[np.ndarray, np.ndarray]:
    """Flat-shaded RGB ``[H, W, 3]`` float32 in [0, 1] and exact ray length ``[H, W]`` float32 (cm).

    Rays go through integer pixel centres with ``K`` (pixel centres at integers).
    """
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij")
    pixels = torch.stack([u.reshape(-1), v.reshape(-1), torch.ones(height * width, dtype=torch.float64)], dim=-1)
    camera_rays = pixels @ torch.linalg.inv(torch.as_tensor(K, dtype=torch.float64)).T
    rays = (camera_rays @ torch.as_tensor(pose[:3, :3], dtype=torch.float64).T).to(device=device, dtype=torch.float32)
    origin = pose[:3, 3]
    inverse = (1 / rays).T.contiguous()  # [3, N]; +-inf for axis-parallel rays is what the slab test wants

    # Inside the room: the ray leaves through the nearest far plane on each axis.
    exits = [torch.where(inverse[k] > 0, (room.size[k] - origin[k]) * inverse[k], -origin[k] * inverse[k]) for k in range(3)]
    t, axis = _min3(*exits)
    positive = torch.stack([inverse[k] > 0 for k in range(3)])
    face = 2 * axis + positive.gather(0, axis[None])[0].long() + len(room.blocks)
    if len(room.blocks):
        # Outside each block: the slab method, entry = latest of the three near planes.
        near, far = [], []
        for k in range(3):
            low = torch.as_tensor(room.blocks[:, 0, k] - origin[k], dtype=torch.float32, device=device)[:, None] * inverse[k]
            high = torch.as_tensor(room.blocks[:, 1, k] - origin[k], dtype=torch.float32, device=device)[:, None] * inverse[k]
            near.append(torch.minimum(low, high))
            far.append(torch.maximum(low, high))
        entry, entry_axis = _max3(*near)
        leave = torch.minimum(torch.minimum(far[0], far[1]), far[2])
        entry = torch.where((entry < leave) & (entry > 0), entry, torch.inf)
        t_block, which = entry.min(dim=0)
        closer = t_block < t
        t = torch.where(closer, t_block, t)
        face = torch.where(closer, which, face)
        axis = torch.where(closer, entry_axis.gather(0, which[None])[0], axis)

    colours = torch.as_tensor(room.colours, device=device, dtype=torch.float32)[face]
    # Light from a fixed direction (not from the camera) and a pattern fixed to the surfaces, so that a
    # surface looks the same from every pose.
    facing = torch.as_tensor(SUN, device=device, dtype=torch.float32)[axis]
    points = torch.as_tensor(origin, dtype=torch.float32, device=device) + t[:, None] * rays
    pattern = 1 + 0.25 * torch.sin(points[:, 0] / 4.0) * torch.sin(points[:, 1] / 4.0 + points[:, 2] / 6.0)
    rgb = (colours * ((0.4 + 0.6 * facing) * pattern)[:, None]).clamp(0, 1)
    length = t * rays.norm(dim=1)
    return rgb.reshape(height, width, 3).cpu().numpy(), length.reshape(height, width).cpu().numpy()


def _min3(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Elementwise minimum of three tensors and which one (0, 1, 2) it came from."""
    ab = torch.minimum(a, b)
    which = torch.where(b < a, 1, 0)
    return torch.minimum(ab, c), torch.where(c < ab, 2, which)


def _max3(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Elementwise maximum of three tensors and which one (0, 1, 2) it came from."""
    ab = torch.maximum(a, b)
    which = torch.where(b > a, 1, 0)
    return torch.maximum(ab, c), torch.where(c > ab, 2, which)
