"""TSDF fusion of depth maps along a camera path into a surface (a mesh and a coloured point cloud), in cm.

A truncated signed distance field on a sparse grid: voxels live in blocks of ``BLOCK``^3 allocated only where a
frame's surface lies (within the truncation distance), so memory follows the surface seen, not the bounding
box of the path. Each frame updates the voxels of the blocks it touches: signed distance ``depth(u, v) - z`` of
the voxel centre along the optical axis (z-depth, OpenCV camera), truncated to ``[-1, 1] x trunc`` and averaged
with weight 1 per observation, as in Curless and Levoy (1996); colours are averaged the same way. Voxels far
behind the observed surface (distance < -trunc) are left alone. The mesh is the zero level set, extracted over the
allocated blocks by scikit-image's marching cubes on a CPU and by our own (``marching_cubes.py``) on a GPU.

Integration is torch arithmetic over whole blocks at a time, on the volume's device (the GPU where reconstruct
runs on one): the blocks a frame touches are found by sorting packed integer keys, looked up in a sorted key
table by binary search, and updated in float32. On a CPU the two passes over pixels and voxels run as compiled
loops instead (``tsdf_loops.py``), to the bit the same arithmetic. We write this rather than use Open3D:
``open3d-cpu`` (0.20) needs the system library ``libusb-1.0``, which a pip install cannot provide, so it fails to
import on a clean machine.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from endoflow.config import ConfigError
from endoflow.io import atomic_path
from endoflow.reconstruction import tsdf_loops
from endoflow.reconstruction.marching_cubes import CORNERS, sparse_marching_cubes

BLOCK = 8  # voxels per block edge
CHUNK_BLOCKS = 8  # blocks per chunk edge when extracting the mesh: 64^3 voxels at a time
# Blocks updated at once: bounded temporaries (about 50 bytes a voxel, 512 voxels a block). On a GPU each pass waits
# for it once, and a 480 px frame touches about 10,000 blocks: one pass there, within half a gigabyte.
UPDATE_BLOCKS = {"cpu": 4096, "cuda": 16384}
# A block's integer coordinates are packed into one int64 key, 21 bits per axis: +-2^20 blocks, 1.7 km at the
# 0.02 cm voxel of 480 px input. Keys sort as their coordinates do (x, then y, then z).
_KEY_BITS = 21
_KEY_HALF = 1 << (_KEY_BITS - 1)
_LOCAL_VOXELS = torch.from_numpy(np.indices((BLOCK,) * 3).reshape(3, -1).T.copy())  # [512, 3], (i, j, k) order


@dataclass
class SurfaceMesh:
    """Vertices ``[V, 3]`` (world, cm), triangles ``[F, 3]`` (vertex indices), colours ``[V, 3]`` uint8 RGB."""

    vertices: np.ndarray
    triangles: np.ndarray
    colours: np.ndarray

    @classmethod
    def empty(cls) -> "SurfaceMesh":
        return cls(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.uint8))


class TSDFVolume:
    """``voxel_cm``: voxel edge; ``trunc_cm``: truncation distance (a few voxels); ``device``: where the voxels live
    and integration runs; ``compiled``: on a CPU, integrate with the compiled loops (False: the tensor code, as on
    a GPU; the same volume, slower). Blocks are rows of the voxel arrays (``[rows, BLOCK^3]``, grown by doubling);
    a sorted table of packed block keys gives each block's row."""

    def __init__(self, voxel_cm: float, trunc_cm: float, device: torch.device | str = "cpu", compiled: bool = True
                 ) -> None:
        if not (voxel_cm > 0 and trunc_cm >= voxel_cm):
            raise ValueError(f"voxel size {voxel_cm} cm must be > 0 and at most the truncation {trunc_cm} cm")
        self.voxel_cm, self.trunc_cm, self.device = float(voxel_cm), float(trunc_cm), torch.device(device)
        self._keys = torch.zeros(0, dtype=torch.int64, device=self.device)  # sorted
        self._rows = torch.zeros(0, dtype=torch.int64, device=self.device)  # the row of each sorted key
        self._tsdf = torch.ones(0, BLOCK**3, device=self.device)
        self._weight = torch.zeros(0, BLOCK**3, device=self.device)
        self._colour = torch.zeros(0, BLOCK**3, 3, device=self.device)
        self._local = _LOCAL_VOXELS.to(self.device, torch.float32)
        self._compiled = compiled and self.device.type == "cpu"
        self._update_blocks = UPDATE_BLOCKS.get(self.device.type, UPDATE_BLOCKS["cpu"])

    @property
    def block_count(self) -> int:
        """Blocks allocated so far (observed by some frame)."""
        return len(self._keys)

    @torch.no_grad()
    def integrate(self, depth_cm: np.ndarray, rgb: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> None:
        """Fuse one frame: ``depth_cm`` ``H x W`` z-depth (0 or non-finite: unknown), ``rgb`` ``H x W x 3``
        uint8, ``K`` its pixel intrinsics, ``T_world_cam`` its camera-to-world pose (cm). Only the blocks near
        this frame's surface are visited, so a frame costs the same however long the video has been."""
        depth = torch.from_numpy(np.ascontiguousarray(  # a view of a transposed array would not flatten
            np.where(np.isfinite(depth_cm) & (depth_cm > 0), depth_cm, 0), np.float32))
        depth = depth.to(self.device)
        keys = self._touched_keys(depth, K, T_world_cam)
        if not len(keys):
            return
        rows = self._rows_of(keys)
        colour = torch.from_numpy(np.ascontiguousarray(rgb)).to(self.device)
        T_cam_world = np.linalg.inv(np.asarray(T_world_cam, np.float64))
        for start in range(0, len(keys), self._update_blocks):
            chunk = slice(start, start + self._update_blocks)
            self._update(keys[chunk], rows[chunk], depth, colour, np.asarray(K, np.float64), T_cam_world)

    def _touched_keys(self, depth: torch.Tensor, K: np.ndarray, T_world_cam: np.ndarray) -> torch.Tensor:
        """Sorted keys of the blocks within ``trunc`` of a surface point of the frame: the points at depth - trunc
        and + trunc along each pixel's ray, and samples between them half a block apart."""
        block_cm = BLOCK * self.voxel_cm
        offsets = np.append(np.arange(-self.trunc_cm, self.trunc_cm + block_cm, block_cm / 2), self.trunc_cm)
        if self._compiled:
            keys, beyond = tsdf_loops.ray_block_keys(depth.numpy(), K, T_world_cam, offsets, block_cm, _KEY_BITS)
            if beyond:
                raise _beyond_key_range()
            return torch.unique(torch.from_numpy(keys))
        v, u = torch.nonzero(depth, as_tuple=True)
        if len(u) == 0:
            return torch.zeros(0, dtype=torch.int64, device=self.device)
        z = depth[v, u]
        rays = torch.stack([(u - float(K[0, 2])) / float(K[0, 0]), (v - float(K[1, 2])) / float(K[1, 1]),
                            torch.ones_like(z)])  # [3, P]
        along = z[None] + torch.tensor(offsets, dtype=torch.float32, device=self.device)[:, None]  # [n, P]
        camera = rays[:, None] * along[None]  # [3, n, P]
        T = torch.from_numpy(T_world_cam).to(self.device, torch.float32)
        blocks = [torch.floor((T[i, 0] * camera[0] + T[i, 1] * camera[1] + T[i, 2] * camera[2] + T[i, 3]) / block_cm)
                  .long().view(-1) for i in range(3)]  # one axis each: no [N, 3] table to stack and pick apart
        # neighbouring pixels of a row mostly share a block: dropping repeats in a row first (one pass) leaves the
        # sort of the full unique a small fraction of the points
        return torch.unique(torch.unique_consecutive(packed_keys(*blocks)))

    def _rows_of(self, keys: torch.Tensor) -> torch.Tensor:
        """The rows of the blocks ``keys`` (sorted, unique), allocating (unobserved: weight 0) those not seen."""
        position = torch.searchsorted(self._keys, keys)
        known = position < len(self._keys)
        known[known.clone()] = self._keys[position[known]] == keys[known]
        rows = torch.empty_like(keys)
        rows[known] = self._rows[position[known]]
        new = ~known
        new_rows = torch.arange(len(self._keys), len(self._keys) + int(new.sum()), device=self.device)
        rows[new] = new_rows
        if len(new_rows):
            self._grow(len(self._keys) + len(new_rows))
            self._insert(keys[new], new_rows)
        return rows

    def _grow(self, rows: int) -> None:
        """Room for ``rows`` blocks, at least doubling, so that a long video reallocates a logarithmic number
        of times."""
        if rows <= len(self._tsdf):
            return
        grown = max(rows, 2 * len(self._tsdf), 64)
        self._tsdf = _enlarged(self._tsdf, grown, 1.0)
        self._weight = _enlarged(self._weight, grown, 0.0)
        self._colour = _enlarged(self._colour, grown, 0.0)

    def _insert(self, keys: torch.Tensor, rows: torch.Tensor) -> None:
        """Merge sorted new ``keys`` (and their ``rows``) into the sorted key table in one pass: each key's place
        in the merged table is its place in its own table plus the keys of the other table before it."""
        old, total = len(self._keys), len(self._keys) + len(keys)
        merged_keys = torch.empty(total, dtype=torch.int64, device=self.device)
        merged_rows = torch.empty(total, dtype=torch.int64, device=self.device)
        new_places = torch.arange(len(keys), device=self.device) + torch.searchsorted(self._keys, keys)
        old_places = torch.arange(old, device=self.device) + torch.searchsorted(keys, self._keys)
        merged_keys[new_places], merged_rows[new_places] = keys, rows
        merged_keys[old_places], merged_rows[old_places] = self._keys, self._rows
        self._keys, self._rows = merged_keys, merged_rows

    def _update(self, keys: torch.Tensor, rows: torch.Tensor, depth: torch.Tensor, colour: torch.Tensor,
                K: np.ndarray, T_cam_world: np.ndarray) -> None:
        """Fuse the frame into the voxels of blocks ``keys`` (at ``rows``) that it sees.

        A voxel's centre is its block's first centre plus a multiple of the voxel edge, and projection before the
        division is linear, so ``K [R | t]`` of every centre is one sum of a per-block and a per-voxel term: the
        arithmetic over all ``n x 512`` voxels is three additions and two divisions. Only the voxels seen are then
        gathered and written."""
        # [3, 4], float64: the per-block terms are large (cm times pixels); skew ignored, as _touched_keys does
        pinhole = np.array([[K[0, 0], 0, K[0, 2]], [0, K[1, 1], K[1, 2]], [0, 0, 1]])
        projection = pinhole @ T_cam_world[:3]
        firsts = (unpack_block_keys(keys).cpu().double().numpy() * BLOCK + 0.5) * self.voxel_cm
        per_block = torch.from_numpy(firsts @ projection[:, :3].T + projection[:, 3]).to(self.device, torch.float32)
        per_voxel = (self._local * self.voxel_cm) @ torch.from_numpy(projection[:, :3].T).to(self.device,
                                                                                           torch.float32)
        if self._compiled:
            tsdf_loops.update_blocks(per_block.numpy(), per_voxel.numpy(), rows.numpy(), depth.numpy(),
                                     colour.numpy(), self._tsdf.numpy(), self._weight.numpy(), self._colour.numpy(),
                                     self.trunc_cm)
            return
        hu, hv, z = (per_block[:, i:i + 1] + per_voxel[:, i] for i in range(3))  # [n, 512] each
        u, v = torch.round(hu / z), torch.round(hv / z)
        height, width = depth.shape
        inside = (z > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        pixel = torch.where(inside, v * width + u, 0).long().view(-1)
        observed = depth.view(-1).index_select(0, pixel).view_as(z)
        sdf = observed - z
        seen = torch.nonzero((inside & (observed > 0) & (sdf >= -self.trunc_cm)).view(-1)).squeeze(1)
        # flat indices of the seen voxels in the voxel arrays, and their pixels (index_select: torch's fast gather)
        fused = rows.repeat_interleave(BLOCK**3).index_select(0, seen) * BLOCK**3 + seen % BLOCK**3
        sdf, pixel = sdf.view(-1).index_select(0, seen), pixel.index_select(0, seen)
        tsdf, weight, colours = self._tsdf.view(-1), self._weight.view(-1), self._colour.view(-1, 3)
        seen_before = weight.index_select(0, fused)
        truncated = torch.clamp(sdf / self.trunc_cm, max=1.0)
        tsdf.index_copy_(0, fused, (tsdf.index_select(0, fused) * seen_before + truncated) / (seen_before + 1))
        rgb = colour.view(-1, 3).index_select(0, pixel).float()
        colours.index_copy_(0, fused, (colours.index_select(0, fused) * seen_before[:, None] + rgb)
                            / (seen_before + 1)[:, None])
        weight.index_copy_(0, fused, seen_before + 1)

    def extract_mesh(self) -> SurfaceMesh:
        """The zero level set of the observed voxels as a triangle mesh, with colours of the nearest voxel: on a CPU
        by :meth:`extract_mesh_on_host`, elsewhere (a GPU) by :meth:`extract_mesh_on_device`. Both have a vertex on
        every crossed cube edge, at the same place and of the same colour; they connect some ambiguous cubes
        differently (:mod:`marching_cubes`). On a CPU scikit-image's took 0.39 of the time of ours
        (docs/benchmarks.md)."""
        return self.extract_mesh_on_host() if self.device.type == "cpu" else self.extract_mesh_on_device()

    def extract_mesh_on_host(self) -> SurfaceMesh:
        """:meth:`extract_mesh` by scikit-image's marching cubes in this process, chunk by chunk
        (:data:`CHUNK_BLOCKS`^3 blocks, plus one voxel layer of the next blocks so that chunks join), so memory
        follows the surface, not the bounding box of a long path."""
        grid = _HostGrid(self)
        parts = [grid.chunk_mesh(index) for index in range(len(grid.chunks))]
        parts = [part for part in parts if len(part.vertices)]
        if not parts:
            return SurfaceMesh.empty()
        offsets = np.cumsum([0] + [len(part.vertices) for part in parts[:-1]])
        return SurfaceMesh(np.concatenate([part.vertices for part in parts]),
                           np.concatenate([part.triangles + offset for part, offset in zip(parts, offsets)]),
                           self._colours_of(np.concatenate([part.voxels for part in parts])))

    def extract_mesh_on_device(self) -> SurfaceMesh:
        """:meth:`extract_mesh` by the volume's own marching cubes, on the volume's device: only the mesh leaves
        it."""
        coords = unpack_block_keys(self._keys)
        mesh = sparse_marching_cubes(coords, self._tsdf, self._weight > 0, self._neighbour_rows(coords))
        return SurfaceMesh(((mesh.vertices + 0.5) * self.voxel_cm).cpu().numpy(), mesh.triangles.cpu().numpy(),
                           self._colours_of(mesh.nearest_voxels))

    def _neighbour_rows(self, coords: torch.Tensor) -> torch.Tensor:
        """``[N, 8]``: for each block of the sorted key table (at ``coords``, its keys unpacked), its row and those of
        the 7 blocks after it (one block further on the axes of the neighbour's corner bits, 4 for x, 2 for y, 1 for
        z), -1 where none is allocated."""
        steps = torch.from_numpy(CORNERS).to(self.device)  # [8, 3]: 0 or 1 block on each axis
        key_steps = CORNERS @ np.array([1 << (2 * _KEY_BITS), 1 << _KEY_BITS, 1])  # on the host: CUDA has no int64 @
        keys = self._keys[:, None] + torch.from_numpy(key_steps).to(self.device)
        # a step from a field at its largest would carry into the next field: no block is there
        beyond = ((coords[:, None, :] == _KEY_HALF - 1) & (steps == 1)).any(-1)
        position = torch.searchsorted(self._keys, keys).clamp(max=max(len(self._keys) - 1, 0))
        found = (self._keys[position] == keys) & ~beyond
        return torch.where(found, self._rows[position], -1)

    def _colours_of(self, voxels: np.ndarray | torch.Tensor) -> np.ndarray:
        """The uint8 colours ``[V, 3]`` of the voxels at flat indices ``voxels [V]`` (``row * BLOCK^3`` plus the
        voxel's place in its block; -1: none, black), gathered where the voxels live: only the surface's colours
        leave a GPU, not the volume's (at 480 px, 60 frames: 370 MB)."""
        index = torch.as_tensor(voxels).to(self.device)
        colours = self._colour.view(-1, 3).index_select(0, index.clamp(min=0))
        colours = torch.where((index >= 0)[:, None], colours, torch.zeros((), device=self.device))
        return colours.round().clamp(0, 255).to(torch.uint8).cpu().numpy()


class _ChunkMesh(NamedTuple):
    """A chunk's part of the mesh: vertices ``[V, 3]`` (world, cm), triangles ``[F, 3]`` (the chunk's vertex
    indices) and each vertex's nearest voxel (flat, as :meth:`TSDFVolume._colours_of` takes them)."""

    vertices: np.ndarray
    triangles: np.ndarray
    voxels: np.ndarray


class _HostGrid:
    """What marching cubes reads of a volume, copied to host memory once: the TSDF and which voxels were observed
    (not the colours: :meth:`TSDFVolume._colours_of` reads those for the vertices alone), with the blocks each
    chunk reads (:func:`_chunk_reads`)."""

    def __init__(self, volume: TSDFVolume) -> None:
        count = volume.block_count
        coords = unpack_block_keys(volume._keys).cpu().numpy()
        rows = volume._rows.cpu().numpy()
        self.tsdf = volume._tsdf[:count].cpu().numpy().reshape(-1, BLOCK, BLOCK, BLOCK)
        self.observed = (volume._weight[:count] > 0).cpu().numpy().reshape(-1, BLOCK, BLOCK, BLOCK)
        self.voxel_cm = volume.voxel_cm
        self.chunks, self.places, self.rows, self.starts = _chunk_reads(coords, rows)

    def chunk_mesh(self, index: int) -> _ChunkMesh:
        """The mesh of chunk ``index`` (of :attr:`chunks`), in world cm, with each vertex's nearest voxel."""
        from skimage.measure import marching_cubes

        empty = _ChunkMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64))
        low = self.chunks[index] * CHUNK_BLOCKS
        size = CHUNK_BLOCKS * BLOCK + 1  # the chunk's voxels and the first layer of the next chunk's
        reads = slice(self.starts[index], self.starts[index + 1])
        places, rows = tuple(self.places[reads].T), self.rows[reads]
        tsdf = _dense(self.tsdf, places, rows, 1.0)
        observed = _dense(self.observed, places, rows, False)
        cubes = observed_cubes(observed)
        if not (cubes.any() and tsdf[observed].min() < 0 < tsdf[observed].max()):
            return empty
        try:
            vertices, triangles, _, _ = marching_cubes(tsdf, level=0.0, mask=cubes)
        except (ValueError, RuntimeError):  # no crossing among the masked cubes
            return empty
        nearest = np.clip(np.round(vertices).astype(np.int64), 0, size - 1)
        world = (vertices + low * BLOCK + 0.5) * self.voxel_cm
        return _ChunkMesh(world, triangles.astype(np.int64), _voxels_at(nearest, places, rows))


def _voxels_at(voxels: np.ndarray, places: tuple[np.ndarray, ...], rows: np.ndarray) -> np.ndarray:
    """The flat indices (``row * BLOCK^3 + i * BLOCK^2 + j * BLOCK + k``) of a chunk's voxels ``voxels [V, 3]``
    (indices into the chunk's voxel grid) whose blocks are ``rows`` at ``places``; -1 where no block is (never
    observed)."""
    row_at = np.full((CHUNK_BLOCKS + 1,) * 3, -1, np.int64)
    row_at[places] = rows
    block, local = np.divmod(voxels, BLOCK)
    row = row_at[block[:, 0], block[:, 1], block[:, 2]]
    flat = row * BLOCK**3 + (local[:, 0] * BLOCK + local[:, 1]) * BLOCK + local[:, 2]
    return np.where(row >= 0, flat, -1)


def _chunk_reads(coords: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Which blocks (integer ``coords [N, 3]`` at ``rows``) each chunk reads, and where: a chunk reads its own
    :data:`CHUNK_BLOCKS`^3 blocks and the first voxel layer of the blocks after it on each axis, so a block at the
    start of a chunk on some axes is also read by the chunks before it on those axes. Returns the chunks holding a
    block ``[C, 3]`` (sorted as tuples: the mesh's order), and the reads grouped by chunk: each one's block place
    in its chunk ``[R, 3]`` (0 to :data:`CHUNK_BLOCKS`) and row ``[R]``; chunk ``c``'s reads are ``starts[c]`` to
    ``starts[c + 1]``."""
    home = np.floor_divide(coords, CHUNK_BLOCKS)
    place = coords - home * CHUNK_BLOCKS
    chunks = np.unique(home, axis=0)
    readers, places, read_rows = [], [], []
    for shift in np.array(list(itertools.product((0, 1), repeat=3))):  # 1 on an axis: the chunk before on it
        read = np.all((shift == 0) | (place == 0), axis=1)
        readers.append(home[read] - shift)
        places.append(place[read] + shift * CHUNK_BLOCKS)
        read_rows.append(rows[read])
    readers, places, read_rows = np.concatenate(readers), np.concatenate(places), np.concatenate(read_rows)
    reader = np.minimum(np.searchsorted(_chunk_keys(chunks), _chunk_keys(readers)), len(chunks) - 1)
    kept = np.all(chunks[reader] == readers, axis=1)  # a chunk holding no block of its own is not meshed
    order = np.argsort(reader[kept], kind="stable")
    return (chunks, places[kept][order], read_rows[kept][order],
            np.searchsorted(reader[kept][order], np.arange(len(chunks) + 1)))


def _chunk_keys(chunks: np.ndarray) -> np.ndarray:
    """One int64 per chunk ``[N, 3]`` that sorts as the chunks do as tuples (21 bits an axis, as block keys)."""
    return packed_keys(*torch.from_numpy(np.ascontiguousarray(chunks.T))).numpy()


def _dense(blocks: np.ndarray, places: tuple[np.ndarray, ...], rows: np.ndarray, fill: float) -> np.ndarray:
    """A chunk's voxels and the first layer of the next chunk's: ``blocks[rows]`` (``[rows, BLOCK, BLOCK, BLOCK]``)
    at block ``places`` (three index arrays, 0 to :data:`CHUNK_BLOCKS`), ``fill`` where no block is."""
    span, size = CHUNK_BLOCKS + 1, CHUNK_BLOCKS * BLOCK + 1
    voxels = np.full((span * BLOCK,) * 3, fill, blocks.dtype)
    voxels.reshape(span, BLOCK, span, BLOCK, span, BLOCK).transpose(0, 2, 4, 1, 3, 5)[places] = blocks[rows]
    return np.ascontiguousarray(voxels[:size, :size, :size])


def _enlarged(rows: torch.Tensor, count: int, fill: float) -> torch.Tensor:
    """``rows`` followed by rows of ``fill`` up to ``count``: one copy and one fill (a concatenation with a filled
    tensor writes the new rows twice)."""
    enlarged = torch.empty((count, *rows.shape[1:]), dtype=rows.dtype, device=rows.device)
    enlarged[:len(rows)] = rows
    enlarged[len(rows):] = fill
    return enlarged


def observed_cubes(observed: np.ndarray) -> np.ndarray:
    """The mask of the cubes whose 8 corners were all observed, for scikit-image's marching cubes, which reads a
    cube's mask at its highest corner (the cube from ``c - 1`` to ``c`` on each axis is ``mask[c]``). A cube
    reaching an unobserved voxel (left at +1) from one behind the surface (-1) would otherwise put a false surface
    at the back of the truncation band."""
    cubes = observed.copy()
    for axis in range(3):
        shifted = np.zeros_like(cubes)
        index = [slice(None)] * 3
        index[axis] = slice(1, None)
        source = [slice(None)] * 3
        source[axis] = slice(0, -1)
        shifted[tuple(index)] = cubes[tuple(source)]
        cubes &= shifted
    return cubes


def pack_block_keys(coords: torch.Tensor) -> torch.Tensor:
    """One int64 key per block of integer coordinates ``coords [N, 3]`` (see :data:`_KEY_BITS`); the pair of
    :func:`unpack_block_keys`. Raises as :func:`packed_keys` does."""
    return packed_keys(*coords.unbind(1))


def packed_keys(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """One int64 key per block, its integer coordinates given axis by axis (int64 tensors of one shape).

    Raises:
        ConfigError: a block lies beyond the keys' range (a path kilometres long at this voxel size).
    """
    if x.numel():  # the six bounds in one transfer: one wait for a GPU, not six
        bounds = torch.stack([bound for axis in (x, y, z) for bound in torch.aminmax(axis)]).tolist()
        if max(-min(bounds), max(bounds)) >= _KEY_HALF:
            raise _beyond_key_range()
    # the fields do not overlap, so products and sums place them as shifts and ors would: torch's int64 shift is not
    # vectorised on a CPU (six times a product's time)
    keys = (x + _KEY_HALF) * (1 << (2 * _KEY_BITS))
    keys += (y + _KEY_HALF) * (1 << _KEY_BITS)
    keys += z + _KEY_HALF
    return keys


def _beyond_key_range() -> ConfigError:
    """The voxel size is the setting at fault (a ConfigError: the command line prints it as an error, not a
    traceback)."""
    return ConfigError(f"a fused point lies more than {_KEY_HALF} blocks from the origin: the camera path is far "
                       f"longer than the voxel size allows; pass a larger --voxel-cm")


def unpack_block_keys(keys: torch.Tensor) -> torch.Tensor:
    """The block coordinates ``[N, 3]`` int64 of keys made by :func:`pack_block_keys`."""
    mask = (1 << _KEY_BITS) - 1
    return torch.stack([(keys >> (2 * _KEY_BITS)) & mask, (keys >> _KEY_BITS) & mask, keys & mask], dim=1) - _KEY_HALF


def write_ply(path: str | Path, vertices: np.ndarray, colours: np.ndarray, triangles: np.ndarray | None = None) -> None:
    """A binary little-endian PLY: vertices (float32 x, y, z in cm) with uint8 RGB, and triangles if given."""
    header = ["ply", "format binary_little_endian 1.0", "comment units: cm; frame: world (camera-to-world poses)",
              f"element vertex {len(vertices)}", "property float x", "property float y", "property float z",
              "property uchar red", "property uchar green", "property uchar blue"]
    if triangles is not None:
        header += [f"element face {len(triangles)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    vertex_rows = np.empty(len(vertices), dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    vertex_rows["xyz"], vertex_rows["rgb"] = vertices, colours
    with atomic_path(path) as temporary, open(temporary, "wb") as out:
        out.write(("\n".join(header) + "\n").encode("ascii"))
        out.write(vertex_rows.tobytes())
        if triangles is not None:
            faces = np.empty(len(triangles), dtype=[("n", "u1"), ("v", "<i4", 3)])
            faces["n"], faces["v"] = 3, triangles
            out.write(faces.tobytes())


def read_ply_vertices(path: str | Path) -> np.ndarray:
    """The vertex positions ``[V, 3]`` of a PLY written by :func:`write_ply`."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    count = next(int(line.split()[2]) for line in data[:end].decode("ascii").splitlines()
                 if line.startswith("element vertex"))
    rows = np.frombuffer(data, dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)], count=count, offset=end)
    return rows["xyz"].astype(np.float64)


