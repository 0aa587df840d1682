"""The TSDF's integration on a CPU as compiled loops (numba): the arithmetic of ``fusion.TSDFVolume``'s tensor code,
in float32 and the same order, so the volume is the same to the bit, in one pass over the pixels and the voxels.

Why loops: on a CPU the tensor code makes some twenty passes over every voxel of the blocks a frame touches (4.5
million at 480 px), each writing a temporary, and the passes run at memory speed. A loop visits each voxel once and
keeps the rest in registers. On a GPU the tensor code is the fast one and stays (``fusion.py``).

The loops run in the calling thread, one core, and release the GIL (``endoflow/compiled.py`` says how they are
compiled and cached).
"""

from __future__ import annotations

import numpy as np

from endoflow.compiled import compiled_loop

_NO_KEY = np.int64(-1)  # packed keys are never negative: each field is offset by half its range
# The keys met last, one per slot of a direct-mapped table (a power of 2): a key found in its slot is not written
# again. A frame's rays touch a few thousand blocks (4,526 at 480 px, with a trained model's depth) but meet them
# about 900,000 times; dropping only a repeat of the key just before left those 894,033 keys to the sort of
# `torch.unique`, which took longer than finding them.
RECENT_KEYS = 1 << 13


def ray_block_keys(depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, offsets_cm: np.ndarray,
                   block_cm: float, key_bits: int) -> tuple[np.ndarray, bool]:
    """The keys (``fusion.packed_keys``, ``key_bits`` per axis) of the blocks holding a point ``depth + offset``
    along the ray of a pixel of known depth, for each of ``offsets_cm``, each at least once, a key left out where
    it was met lately (:data:`RECENT_KEYS`; unsorted, not unique: ``fusion.TSDFVolume._touched_keys`` makes them
    so); and whether a block lay beyond the keys' range. ``depth`` ``H x W`` float32 (0: unknown)."""
    intrinsics = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float32)
    keys, count, beyond = _ray_block_keys(np.ascontiguousarray(depth, np.float32), intrinsics,
                                          np.ascontiguousarray(T_world_cam, np.float32),
                                          np.ascontiguousarray(offsets_cm, np.float32), np.float32(block_cm),
                                          key_bits, RECENT_KEYS)
    return keys[:count].copy(), bool(beyond)


def update_blocks(per_block: np.ndarray, per_voxel: np.ndarray, rows: np.ndarray, depth: np.ndarray,
                  colour: np.ndarray, tsdf: np.ndarray, weight: np.ndarray, colours: np.ndarray,
                  trunc_cm: float) -> None:
    """Fuse one frame into the voxels of blocks at ``rows`` (distinct) in place: ``fusion.TSDFVolume._update`` on a
    CPU. ``per_block [n, 3]`` and ``per_voxel [512, 3]`` float32: the two terms of each voxel centre's projection
    ``(u z, v z, z)``; ``depth`` ``H x W`` float32, ``colour`` ``H x W x 3`` uint8; ``tsdf``, ``weight``
    ``[rows, 512]`` and ``colours`` ``[rows, 512, 3]`` float32, the volume's arrays."""
    _update_voxels(per_block, per_voxel, rows, depth, colour, tsdf, weight, colours, np.float32(trunc_cm))


@compiled_loop
def _ray_block_keys(depth, intrinsics, T, offsets, block_cm, key_bits, recent_keys):  # pragma: no cover (compiled)
    """The keys of the pixels' ray points, those met lately dropped, and their count; and whether any block lay
    beyond the keys' range."""
    height, width = depth.shape
    half = np.int64(1) << (key_bits - 1)
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    keys = np.empty(height * width * len(offsets), np.int64)
    recent = np.full(recent_keys, _NO_KEY)
    count, beyond = 0, False
    for v in range(height):
        ry = (np.float32(v) - cy) / fy
        for u in range(width):
            z = depth[v, u]
            if z == 0:
                continue
            rx = (np.float32(u) - cx) / fx
            for offset in offsets:
                along = z + offset
                x, y = rx * along, ry * along
                packed, slot = np.int64(0), np.int64(0)
                for axis in range(3):
                    world = T[axis, 0] * x + T[axis, 1] * y + T[axis, 2] * along + T[axis, 3]
                    block = np.int64(np.floor(world / block_cm))
                    if block >= half or block <= -half:  # as fusion.packed_keys refuses
                        beyond = True
                    packed = (packed << key_bits) + (block + half)
                    slot = slot * 31 + block  # neighbouring blocks fall in different slots
                slot &= recent_keys - 1
                if recent[slot] != packed:
                    recent[slot] = packed
                    keys[count] = packed
                    count += 1
    return keys, count, beyond


@compiled_loop
def _update_voxels(per_block, per_voxel, rows, depth, colour, tsdf, weight, colours, trunc):  # pragma: no cover
    """Each voxel of each block that projects into the image onto known depth no farther than ``trunc`` behind it:
    its truncated signed distance and colour averaged in, its weight counted up."""
    height, width = depth.shape
    one = np.float32(1)
    for block in range(len(rows)):
        row = rows[block]
        for voxel in range(len(per_voxel)):
            z = per_block[block, 2] + per_voxel[voxel, 2]
            if not z > 0:  # behind the camera, or in its plane: numba's float division by 0 raises
                continue
            u = np.rint((per_block[block, 0] + per_voxel[voxel, 0]) / z)
            v = np.rint((per_block[block, 1] + per_voxel[voxel, 1]) / z)
            if not (0 <= u < width and 0 <= v < height):
                continue
            pixel_v, pixel_u = np.int64(v), np.int64(u)
            observed = depth[pixel_v, pixel_u]
            sdf = observed - z
            if not (observed > 0 and sdf >= -trunc):
                continue
            seen_before = weight[row, voxel]
            tsdf[row, voxel] = (tsdf[row, voxel] * seen_before + min(sdf / trunc, one)) / (seen_before + one)
            for channel in range(3):
                colours[row, voxel, channel] = ((colours[row, voxel, channel] * seen_before
                                                 + np.float32(colour[pixel_v, pixel_u, channel]))
                                                / (seen_before + one))
            weight[row, voxel] = seen_before + one
