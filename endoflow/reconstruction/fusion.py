"""TSDF fusion of depth maps along a camera path into a surface (a mesh and a coloured point cloud), in cm.

A truncated signed distance field on a sparse grid: voxels live in blocks of ``BLOCK``^3 allocated only where a
frame's surface lies (within the truncation distance), so memory follows the surface seen, not the bounding
box of the path. Each frame updates the voxels of the blocks it touches: signed distance ``depth(u, v) - z`` of
the voxel centre along the optical axis (z-depth, OpenCV camera), truncated to ``[-1, 1] x trunc`` and averaged
with weight 1 per observation, as in Curless and Levoy (1996); colours are averaged the same way. Voxels far
behind the observed surface (distance < -trunc) are left alone. The mesh is the zero level set, extracted with
scikit-image's marching cubes over the allocated blocks.

We write this rather than use Open3D: ``open3d-cpu`` (0.20) needs the system library ``libusb-1.0``, which a pip
install cannot provide, so it fails to import on a clean machine.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from endoflow.io import atomic_path

BLOCK = 8  # voxels per block edge
CHUNK_BLOCKS = 8  # blocks per chunk edge when extracting the mesh: 64^3 voxels at a time


@dataclass
class SurfaceMesh:
    """Vertices ``[V, 3]`` (world, cm), triangles ``[F, 3]`` (vertex indices), colours ``[V, 3]`` uint8 RGB."""

    vertices: np.ndarray
    triangles: np.ndarray
    colours: np.ndarray


@dataclass
class TSDFVolume:
    """``voxel_cm``: voxel edge; ``trunc_cm``: truncation distance (a few voxels). ``blocks`` maps a block's
    integer coordinates to its row in the voxel arrays (``[rows, BLOCK^3]``, grown by doubling)."""

    voxel_cm: float
    trunc_cm: float
    blocks: dict[tuple[int, int, int], int] = field(default_factory=dict)
    _tsdf: np.ndarray = field(default_factory=lambda: np.ones((0, BLOCK**3), np.float32))
    _weight: np.ndarray = field(default_factory=lambda: np.zeros((0, BLOCK**3), np.float32))
    _colour: np.ndarray = field(default_factory=lambda: np.zeros((0, BLOCK**3, 3), np.float32))

    def __post_init__(self) -> None:
        if not (self.voxel_cm > 0 and self.trunc_cm >= self.voxel_cm):
            raise ValueError(f"voxel size {self.voxel_cm} cm must be > 0 and at most the truncation "
                             f"{self.trunc_cm} cm")

    def integrate(self, depth_cm: np.ndarray, rgb: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> None:
        """Fuse one frame: ``depth_cm`` ``H x W`` z-depth (0 or non-finite: unknown), ``rgb`` ``H x W x 3``
        uint8, ``K`` its pixel intrinsics, ``T_world_cam`` its camera-to-world pose (cm). Only the blocks near
        this frame's surface are visited, so a frame costs the same however long the video has been."""
        depth = np.where(np.isfinite(depth_cm) & (depth_cm > 0), depth_cm, 0.0).astype(np.float64)
        touched = sorted(self._touched_blocks(depth, K, T_world_cam))
        if not touched:
            return
        keys = np.array(touched, dtype=np.int64)
        rows = np.array([self._row(key) for key in touched])
        T_cam_world = np.linalg.inv(T_world_cam)
        for start in range(0, len(keys), 4096):  # bounded temporaries: 4096 blocks of 512 voxels at a time
            self._update(keys[start:start + 4096], rows[start:start + 4096], depth, rgb, K, T_cam_world)

    def _touched_blocks(self, depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> set[tuple[int, int, int]]:
        """Blocks within ``trunc`` of a surface point of the frame: the points at depth - trunc and + trunc along
        each pixel's ray, and samples between them one block apart."""
        v, u = np.nonzero(depth)
        if len(u) == 0:
            return set()
        z = depth[v, u]
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(z)], axis=1)
        block_cm = BLOCK * self.voxel_cm
        steps = np.arange(-self.trunc_cm, self.trunc_cm + block_cm, block_cm / 2)
        touched: set[tuple[int, int, int]] = set()
        for offset in np.append(steps, self.trunc_cm):
            points = rays * (z + offset)[:, None]
            world = points @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
            touched.update(map(tuple, np.unique(np.floor(world / block_cm).astype(np.int64), axis=0)))
        return touched

    def _row(self, key: tuple[int, int, int]) -> int:
        """The block's row in the voxel arrays, allocated (unobserved: weight 0) on first use."""
        if key not in self.blocks:
            if len(self.blocks) == len(self._tsdf):
                grow = max(64, len(self._tsdf))
                self._tsdf = np.concatenate([self._tsdf, np.ones((grow, BLOCK**3), np.float32)])
                self._weight = np.concatenate([self._weight, np.zeros((grow, BLOCK**3), np.float32)])
                self._colour = np.concatenate([self._colour, np.zeros((grow, BLOCK**3, 3), np.float32)])
            self.blocks[key] = len(self.blocks)
        return self.blocks[key]

    def _update(self, keys: np.ndarray, rows: np.ndarray, depth: np.ndarray, rgb: np.ndarray, K: np.ndarray,
                T_cam_world: np.ndarray) -> None:
        centres = voxel_centres(keys, self.voxel_cm)  # [n, 512, 3]
        cam = centres @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        z = cam[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.round(K[0, 0] * cam[..., 0] / z + K[0, 2])
            v = np.round(K[1, 1] * cam[..., 1] / z + K[1, 2])
        height, width = depth.shape
        inside = (z > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        ui, vi = np.where(inside, u, 0).astype(np.int64), np.where(inside, v, 0).astype(np.int64)
        observed = depth[vi, ui]
        sdf = observed - z
        block, voxel = np.nonzero(inside & (observed > 0) & (sdf >= -self.trunc_cm))
        row = rows[block]
        w = self._weight[row, voxel]
        self._tsdf[row, voxel] = (self._tsdf[row, voxel] * w
                                  + np.minimum(sdf[block, voxel] / self.trunc_cm, 1.0)) / (w + 1)
        pixels = rgb[vi[block, voxel], ui[block, voxel]]
        self._colour[row, voxel] = (self._colour[row, voxel] * w[:, None] + pixels) / (w + 1)[:, None]
        self._weight[row, voxel] = w + 1

    def extract_mesh(self) -> SurfaceMesh:
        """The zero level set of the observed voxels as a triangle mesh, with colours of the nearest voxel.

        Extracted chunk by chunk (:data:`CHUNK_BLOCKS`^3 blocks, plus one voxel layer of the next blocks so that
        chunks join), so memory follows the surface, not the bounding box of a long path."""
        parts = [self._chunk_mesh(chunk) for chunk in sorted({tuple(k // CHUNK_BLOCKS for k in key)
                                                             for key in self.blocks})]
        parts = [part for part in parts if len(part.vertices)]
        if not parts:
            return SurfaceMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.uint8))
        offsets = np.cumsum([0] + [len(part.vertices) for part in parts[:-1]])
        return SurfaceMesh(np.concatenate([part.vertices for part in parts]),
                           np.concatenate([part.triangles + offset for part, offset in zip(parts, offsets)]),
                           np.concatenate([part.colours for part in parts]))

    def _chunk_mesh(self, chunk: tuple[int, int, int]) -> SurfaceMesh:
        from skimage.measure import marching_cubes

        empty = SurfaceMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.uint8))
        low = np.array(chunk) * CHUNK_BLOCKS
        size = CHUNK_BLOCKS * BLOCK + 1  # the chunk's voxels and the first layer of the next chunk's
        tsdf = np.ones((size,) * 3, np.float32)
        weight = np.zeros((size,) * 3, np.float32)
        colour = np.zeros((size,) * 3 + (3,), np.float32)
        for offset in np.ndindex(*(CHUNK_BLOCKS + 1,) * 3):
            row = self.blocks.get(tuple(int(v) for v in low + offset))
            if row is None:
                continue
            region = tuple(slice(o * BLOCK, min(o * BLOCK + BLOCK, size)) for o in offset)
            extent = tuple(r.stop - r.start for r in region)
            tsdf[region] = self._tsdf[row].reshape(BLOCK, BLOCK, BLOCK)[:extent[0], :extent[1], :extent[2]]
            weight[region] = self._weight[row].reshape(BLOCK, BLOCK, BLOCK)[:extent[0], :extent[1], :extent[2]]
            colour[region] = self._colour[row].reshape(BLOCK, BLOCK, BLOCK, 3)[:extent[0], :extent[1], :extent[2]]
        observed = weight > 0
        cubes = observed_cubes(observed)
        if not (cubes.any() and tsdf[observed].min() < 0 < tsdf[observed].max()):
            return empty
        try:
            vertices, triangles, _, _ = marching_cubes(tsdf, level=0.0, mask=cubes)
        except (ValueError, RuntimeError):  # no crossing among the masked cubes
            return empty
        nearest = np.clip(np.round(vertices).astype(np.int64), 0, size - 1)
        colours = colour[nearest[:, 0], nearest[:, 1], nearest[:, 2]]
        world = (vertices + low * BLOCK + 0.5) * self.voxel_cm
        return SurfaceMesh(world, triangles.astype(np.int64), np.clip(np.round(colours), 0, 255).astype(np.uint8))


def observed_cubes(observed: np.ndarray) -> np.ndarray:
    """Cubes (named by their lowest corner) whose 8 corners were all observed. Marching cubes reads its mask at a
    cube's lowest corner only; a cube reaching an unobserved voxel (left at +1) from one behind the surface (-1)
    would otherwise put a false surface at the back of the truncation band."""
    cubes = observed.copy()
    for axis in range(3):
        shifted = np.zeros_like(cubes)
        index = [slice(None)] * 3
        index[axis] = slice(0, -1)
        source = [slice(None)] * 3
        source[axis] = slice(1, None)
        shifted[tuple(index)] = cubes[tuple(source)]
        cubes &= shifted
    return cubes


def voxel_centres(keys: np.ndarray, voxel_cm: float) -> np.ndarray:
    """``[n, BLOCK^3, 3]`` world centres (cm) of the voxels of blocks ``keys`` ``[n, 3]``, voxels in the order of
    ``np.indices((BLOCK,) * 3)`` (the order a block is stored in and reshaped from)."""
    local = np.indices((BLOCK, BLOCK, BLOCK)).reshape(3, -1).T  # [512, 3], (i, j, k)
    return ((keys[:, None, :] * BLOCK + local[None]) + 0.5) * voxel_cm


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


