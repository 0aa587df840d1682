"""Marching cubes in torch over a sparse block volume, on the device where the volume lives.

On a GPU, extracting the surface with scikit-image meant copying the volume to the host and meshing it chunk by
chunk in one thread (its marching cubes holds Python's lock): at 480 px that took about half of a frame's time.
Here every cube of a batch of blocks is meshed at once with tensor arithmetic, and only the mesh leaves the device.

The triangles of each of the 256 corner cases are built below from one rule rather than copied from a published
table. The surface crosses a cube face between the face's inside and outside corners (inside: TSDF < 0); on a face
whose two inside corners are diagonal (four crossings), each inside corner is cut off on its own. The rule depends
only on the face's four values, so the two cubes sharing a face cut it alike and the surface has no cracks. The
crossings on a cube's faces join into closed loops, each a fan of triangles wound as scikit-image winds them: the
normal ``(b - a) x (c - a)`` points to increasing TSDF, out of the tissue. The vertices are scikit-image's on every
crossed cube edge; its Lewiner variant also adds a point inside some ambiguous cubes and triangulates those
differently.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np
import torch

BLOCK = 8  # voxels per block edge of the sparse volume (fusion.py's TSDFVolume)
BLOCKS_PER_BATCH = 4096  # a batch's corner values: 4096 x 512 cubes x 8 corners, 64 MB of float32
_CORNERS = np.array(list(itertools.product((0, 1), repeat=3)))  # [8, 3]: corner c is (i, j, k), c = 4i + 2j + k
# edges as (low corner, axis): a corner and the one one step along the axis; 12 of them
_EDGES = [(corner, axis) for corner in range(8) for axis in range(3) if _CORNERS[corner][axis] == 0]


class SparseMesh(NamedTuple):
    """A mesh on the volume's device: vertices ``[V, 3]`` float64 in voxel units (a voxel's centre at its
    integer index), triangles ``[F, 3]`` int64, and each vertex's nearest voxel as a flat index into the volume's
    voxel arrays (``row * BLOCK^3 + place in the block``)."""

    vertices: torch.Tensor
    triangles: torch.Tensor
    nearest_voxels: torch.Tensor


def _edge_index(a: int, b: int) -> int:
    """The index in :data:`_EDGES` of the edge between corners ``a`` and ``b``."""
    low, high = min(a, b), max(a, b)
    return _EDGES.index((low, int(np.argmax(_CORNERS[high] - _CORNERS[low]))))


def _faces() -> list[tuple[np.ndarray, list[int]]]:
    """Each cube face as its outward normal and its four corners in order around it."""
    faces = []
    for axis, side in itertools.product(range(3), (0, 1)):
        others = [a for a in range(3) if a != axis]
        ring = []
        for u, v in ((0, 0), (1, 0), (1, 1), (0, 1)):
            position = np.zeros(3, int)
            position[axis], position[others[0]], position[others[1]] = side, u, v
            ring.append(int(position @ [4, 2, 1]))
        normal = np.zeros(3)
        normal[axis] = 1.0 if side else -1.0
        faces.append((normal, ring))
    return faces


def _face_segments(inside: list[bool], ring: list[int]) -> list[tuple[list[int], list[int]]]:
    """The crossings of one face joined into segments: each segment's two edges (as corner pairs) and the inside
    corners it cuts off from the rest of the face."""
    edges = [(ring[i], ring[(i + 1) % 4]) for i in range(4)]
    crossing = [i for i, (a, b) in enumerate(edges) if inside[a] != inside[b]]
    inner = [c for c in ring if inside[c]]
    if len(crossing) == 2:
        return [([*edges[crossing[0]]], [*edges[crossing[1]]], inner)]
    if len(crossing) == 4:  # inside corners diagonal: each cut off on its own
        segments = []
        for place, corner in enumerate(ring):
            if inside[corner]:
                segments.append(([*edges[(place - 1) % 4]], [*edges[place]], [corner]))
        return segments
    return []


def _case_triangles(case: int, faces: list[tuple[np.ndarray, list[int]]]) -> list[tuple[int, int, int]]:
    """The triangles (edge indices) of the cube whose inside corners are the bits of ``case``."""
    inside = [bool(case >> c & 1) for c in range(8)]
    centre = np.full(3, 0.5)
    following: dict[int, int] = {}
    for normal, ring in faces:
        for first, second, inner in _face_segments(inside, ring):
            a, b = _edge_index(*first), _edge_index(*second)
            start, end = _CORNERS[first].mean(0), _CORNERS[second].mean(0)
            outward = (start + end) / 2 - _CORNERS[inner].mean(0)  # toward increasing TSDF
            # the loop runs anticlockwise seen from outside its tissue: the cube's inside lies to its left
            if np.cross(outward, end - start) @ (centre - (start + end) / 2) < 0:
                a, b = b, a
            assert a not in following, f"case {case}: edge {a} starts two segments"
            following[a] = b
    triangles = []
    while following:
        loop = [next(iter(following))]
        after = following.pop(loop[0])
        while after != loop[0]:
            loop.append(after)
            after = following.pop(after)
        triangles += [(loop[0], loop[i], loop[i + 1]) for i in range(1, len(loop) - 1)]
    return triangles


def _triangle_table() -> torch.Tensor:
    """``[256, T, 3]`` int64: each case's triangles as edge indices, padded with -1."""
    faces = _faces()
    cases = [_case_triangles(case, faces) for case in range(256)]
    table = torch.full((256, max(map(len, cases)), 3), -1, dtype=torch.int64)
    for case, triangles in enumerate(cases):
        if triangles:
            table[case, :len(triangles)] = torch.tensor(triangles)
    return table


TRIANGLES = _triangle_table()
_PATCH = BLOCK + 1  # a block's voxels and the first layer of the blocks after it: its cubes' corners


def _patch_sources() -> tuple[torch.Tensor, torch.Tensor]:
    """For each voxel of a block's patch (``_PATCH^3``, flat): which neighbour holds it (0-7, as corner bits:
    the block itself, or the block after it on some axes) and its place in that block (flat)."""
    place = torch.from_numpy(np.indices((_PATCH,) * 3).reshape(3, -1).T.copy())  # [729, 3]
    neighbour = (place // BLOCK) @ torch.tensor([4, 2, 1])
    local = (place % BLOCK) @ torch.tensor([BLOCK * BLOCK, BLOCK, 1])
    return neighbour, local


def _cube_corners() -> torch.Tensor:
    """``[BLOCK^3, 8]``: the patch voxels (flat) at the 8 corners of each cube whose lowest corner is a block
    voxel."""
    low = torch.from_numpy(np.indices((BLOCK,) * 3).reshape(3, -1).T.copy())  # [512, 3]
    corners = low[:, None, :] + torch.from_numpy(_CORNERS)[None]  # [512, 8, 3]
    return corners @ torch.tensor([_PATCH * _PATCH, _PATCH, 1])


_NEIGHBOUR, _LOCAL = _patch_sources()
_CUBE_CORNERS = _cube_corners()
_EDGE_CORNERS = torch.tensor([[corner, corner + (4, 2, 1)[axis]] for corner, axis in _EDGES])  # [12, 2]
_EDGE_AXES = torch.tensor([axis for _, axis in _EDGES])
_CORNER_BITS = 1 << torch.arange(8)


@torch.no_grad()
def sparse_marching_cubes(coords: torch.Tensor, tsdf: torch.Tensor, observed: torch.Tensor,
                          neighbour_rows: torch.Tensor) -> SparseMesh:
    """The zero level set of a sparse block volume, over the cubes whose 8 corners were all observed.

    ``coords [N, 3]``: the blocks' integer coordinates; ``tsdf``, ``observed`` ``[rows, BLOCK^3]``: the voxels,
    a block to a row; ``neighbour_rows [N, 8]``: the row of each block and of the 7 blocks after it (one further on
    the axes of the corner bits: 4 for x, 2 for y, 1 for z), -1 where none is. Vertices are shared between the
    cubes and blocks that meet at them; their order is their edges' (row, place, axis) order."""
    device = tsdf.device
    edge_keys, positions, nearest = [], [], []
    for start in range(0, len(coords), BLOCKS_PER_BATCH):
        batch = slice(start, start + BLOCKS_PER_BATCH)
        meshed = _batch_crossings(coords[batch], neighbour_rows[batch], tsdf, observed)
        if meshed is not None:
            for gathered, part in zip((edge_keys, positions, nearest), meshed):
                gathered.append(part)
    if not edge_keys:
        empty = torch.zeros(0, 3, device=device)
        return SparseMesh(empty.double(), empty.long(), torch.zeros(0, dtype=torch.int64, device=device))
    edge_keys, inverse = torch.unique(torch.cat(edge_keys), return_inverse=True)
    vertices = torch.empty(len(edge_keys), 3, dtype=torch.float64, device=device)
    vertices[inverse] = torch.cat(positions)  # an edge shared by several cubes: the same value from each
    voxels = torch.empty(len(edge_keys), dtype=torch.int64, device=device)
    voxels[inverse] = torch.cat(nearest)
    return SparseMesh(vertices, triangles=inverse.view(-1, 3), nearest_voxels=voxels)


def _batch_crossings(coords: torch.Tensor, neighbour_rows: torch.Tensor, tsdf: torch.Tensor, observed: torch.Tensor
                     ) -> tuple[torch.Tensor, ...] | None:
    """A batch of blocks meshed: the corners of its triangles, three at a time, each as its edge's key (``flat
    voxel * 3 + axis`` of the edge's low end), position (voxel units, float64) and nearest voxel (flat). None
    when no cube of the batch holds surface."""
    device = tsdf.device
    sources = neighbour_rows[:, _NEIGHBOUR.to(device)]  # [B, 729] rows
    flat = sources * BLOCK**3 + _LOCAL.to(device)
    present = sources >= 0
    flat = torch.where(present, flat, 0)
    values = tsdf.view(-1)[flat]
    seen = observed.view(-1)[flat] & present
    corners = _CUBE_CORNERS.to(device)
    corner_values, corner_seen = values[:, corners], seen[:, corners]  # [B, 512, 8]
    case = ((corner_values < 0).long() * _CORNER_BITS.to(device)).sum(-1)
    surface = corner_seen.all(-1) & (case > 0) & (case < 255)
    block, cube = torch.nonzero(surface, as_tuple=True)
    if not len(block):
        return None
    table = TRIANGLES.to(device)[case[block, cube]]  # [n, T, 3] edges
    kept = table[..., 0] >= 0
    owner = torch.arange(len(block), device=device)[:, None].expand(kept.shape)[kept]  # [F]
    triangle_edges = table[kept]  # [F, 3]
    # each triangle corner's edge, as (cube, edge): its ends' patch voxels
    cube_of, edge = owner[:, None].expand_as(triangle_edges).reshape(-1), triangle_edges.reshape(-1)
    ends = corners[cube[cube_of]][torch.arange(len(edge), device=device)[:, None], _EDGE_CORNERS.to(device)[edge]]
    low_flat, high_flat = flat[block[cube_of], ends[:, 0]], flat[block[cube_of], ends[:, 1]]
    low_value, high_value = values[block[cube_of], ends[:, 0]], values[block[cube_of], ends[:, 1]]
    low_value, high_value = low_value.double(), high_value.double()
    t = low_value / (low_value - high_value)  # where the TSDF crosses 0 between the ends
    axis = _EDGE_AXES.to(device)[edge]
    low_voxel = coords[block[cube_of]] * BLOCK + _unflatten(ends[:, 0])
    position = low_voxel.double()
    position[torch.arange(len(axis), device=device), axis] += t
    nearest = torch.where(t <= 0.5, low_flat, high_flat)
    return low_flat * 3 + axis, position, nearest


def _unflatten(patch_voxels: torch.Tensor) -> torch.Tensor:
    """Patch voxel places (flat) as ``[n, 3]`` (i, j, k)."""
    return torch.stack([patch_voxels // (_PATCH * _PATCH), patch_voxels // _PATCH % _PATCH,
                        patch_voxels % _PATCH], dim=1)
