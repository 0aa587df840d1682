"""Marching cubes in torch over a sparse block volume, on the device where the volume lives.

On a GPU, extracting the surface with scikit-image meant copying the volume to the host and meshing it chunk by
chunk in one thread (its marching cubes holds Python's lock): at 480 px, 1.9 s of a 5.1 s call of 60 frames
(docs/benchmarks.md). Here every cube of a batch of blocks is meshed at once with tensor arithmetic, and only the
mesh leaves the device.

The triangles of each of the 256 corner cases are built below from one rule rather than copied from a published
table. The surface crosses a cube face between the face's inside and outside corners (inside: TSDF < 0); on a face
whose two inside corners are diagonal (four crossings), each inside corner is cut off on its own. The rule depends
only on the face's four values, so the two cubes sharing a face cut it alike and the surface has no cracks. The
crossings on a cube's faces join into closed loops, each a fan of triangles wound as scikit-image winds them: the
normal ``(b - a) x (c - a)`` points to increasing TSDF, out of the tissue. The vertices are scikit-image's on every
crossed cube edge, and each takes the colour of the same nearest voxel; scikit-image's Lewiner variant decides an
ambiguous face from its values (it may join the two inside corners) and adds a point inside some ambiguous cubes, so
there the two meshes can connect differently.
"""

from __future__ import annotations

import functools
import itertools
from typing import NamedTuple

import numpy as np
import torch

# Blocks meshed at once. A batch's temporaries are some 40 bytes a cube (the corners' values, indices and flags),
# 512 cubes a block: about 80 MB for 4096 blocks. Its crossings are merged within the batch before the next.
BLOCKS_PER_BATCH = 4096
CORNERS = np.array(list(itertools.product((0, 1), repeat=3)))  # [8, 3]: corner c is (i, j, k), c = 4i + 2j + k
CORNER_WEIGHTS = np.array([4, 2, 1])  # a corner's (i, j, k) dotted with these: its index
# edges as (low corner, axis): a corner and the one one step along the axis; 12 of them
_EDGES = [(corner, axis) for corner in range(8) for axis in range(3) if CORNERS[corner][axis] == 0]


class SparseMesh(NamedTuple):
    """A mesh on the volume's device: vertices ``[V, 3]`` float64 in voxel units (a voxel's centre at its
    integer index), triangles ``[F, 3]`` int64, and each vertex's nearest voxel as a flat index into the volume's
    voxel arrays (``row * block^3 + place in the block``; halfway between two voxels, the one at an even index on
    the edge's axis, as numpy rounds)."""

    vertices: torch.Tensor
    triangles: torch.Tensor
    nearest_voxels: torch.Tensor


def _edge_index(a: int, b: int) -> int:
    """The index in :data:`_EDGES` of the edge between corners ``a`` and ``b``."""
    low, high = min(a, b), max(a, b)
    return _EDGES.index((low, int(np.argmax(CORNERS[high] - CORNERS[low]))))


def _faces() -> list[list[int]]:
    """Each cube face as its four corners in order around it."""
    faces = []
    for axis, side in itertools.product(range(3), (0, 1)):
        others = [a for a in range(3) if a != axis]
        ring = []
        for u, v in ((0, 0), (1, 0), (1, 1), (0, 1)):
            position = np.zeros(3, int)
            position[axis], position[others[0]], position[others[1]] = side, u, v
            ring.append(int(position @ CORNER_WEIGHTS))
        faces.append(ring)
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


def _case_triangles(case: int, faces: list[list[int]]) -> list[tuple[int, int, int]]:
    """The triangles (edge indices) of the cube whose inside corners are the bits of ``case``."""
    inside = [bool(case >> c & 1) for c in range(8)]
    centre = np.full(3, 0.5)
    following: dict[int, int] = {}
    for ring in faces:
        for first, second, inner in _face_segments(inside, ring):
            a, b = _edge_index(*first), _edge_index(*second)
            start, end = CORNERS[first].mean(0), CORNERS[second].mean(0)
            outward = (start + end) / 2 - CORNERS[inner].mean(0)  # toward increasing TSDF
            # the loop runs anticlockwise seen from outside its tissue: the cube's inside lies to its left
            if np.cross(outward, end - start) @ (centre - (start + end) / 2) < 0:
                a, b = b, a
            if a in following:  # the rule above failed: no table rather than a surface with holes
                raise AssertionError(f"marching cubes case {case}: edge {a} starts two segments")
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


class _Tables(NamedTuple):
    """Index tables for blocks of ``block^3`` voxels, on one device. A block's patch is its voxels and the first
    layer of the blocks after it (``(block + 1)^3``, flat): the corners of the cubes whose lowest corner is one of
    its voxels."""

    neighbour: torch.Tensor  # [patch]: the block holding each patch voxel, 0-7 as corner bits (0: the block itself)
    local: torch.Tensor  # [patch]: its place in that block (flat)
    cube_corners: torch.Tensor  # [block^3, 8]: the patch voxels at each cube's corners
    edge_corners: torch.Tensor  # [12, 2]: the corners at the ends of each edge
    edge_axes: torch.Tensor  # [12]
    corner_bits: torch.Tensor  # [8]: 1 << corner
    triangles: torch.Tensor  # TRIANGLES


@functools.lru_cache(maxsize=4)
def _tables(block: int, device: torch.device) -> _Tables:
    patch = block + 1
    place = torch.from_numpy(np.indices((patch,) * 3).reshape(3, -1).T.copy())
    weights = torch.from_numpy(CORNER_WEIGHTS)
    low = torch.from_numpy(np.indices((block,) * 3).reshape(3, -1).T.copy())
    corners = low[:, None, :] + torch.from_numpy(CORNERS)[None]
    edge_ends = [[corner, corner + int(CORNER_WEIGHTS[axis])] for corner, axis in _EDGES]
    tables = _Tables(neighbour=(place // block) @ weights, local=(place % block) @ torch.tensor([block**2, block, 1]),
                     cube_corners=corners @ torch.tensor([patch**2, patch, 1]), edge_corners=torch.tensor(edge_ends),
                     edge_axes=torch.tensor([axis for _, axis in _EDGES]), corner_bits=1 << torch.arange(8),
                     triangles=TRIANGLES)
    return _Tables(*(table.to(device) for table in tables))


class _Crossings(NamedTuple):
    """A batch's distinct crossed edges: keys (``flat voxel * 3 + axis`` of the edge's low end), positions
    ``[E, 3]`` (voxel units, float64) and nearest voxels (flat); and its triangles ``[F, 3]`` as indices into
    them."""

    keys: torch.Tensor
    positions: torch.Tensor
    nearest: torch.Tensor
    triangles: torch.Tensor


@torch.no_grad()
def sparse_marching_cubes(coords: torch.Tensor, tsdf: torch.Tensor, observed: torch.Tensor,
                          neighbour_rows: torch.Tensor) -> SparseMesh:
    """The zero level set of a sparse block volume, over the cubes whose 8 corners were all observed.

    ``coords [N, 3]``: the blocks' integer coordinates; ``tsdf``, ``observed`` ``[rows, block^3]``: the voxels,
    a block to a row; ``neighbour_rows [N, 8]``: the row of each block and of the 7 blocks after it (one further on
    the axes of the corner bits: 4 for x, 2 for y, 1 for z), -1 where none is. Vertices are shared between the
    cubes and blocks that meet at them; their order is their edges' (row, place, axis) order."""
    device = tsdf.device
    block = round(tsdf.shape[1] ** (1 / 3))
    tables = _tables(block, device)
    parts = []
    for start in range(0, len(coords), BLOCKS_PER_BATCH):
        batch = slice(start, start + BLOCKS_PER_BATCH)
        part = _batch_crossings(coords[batch], neighbour_rows[batch], tsdf, observed, block, tables)
        if part is not None:
            parts.append(part)
    if not parts:
        empty = torch.zeros(0, 3, device=device)
        return SparseMesh(empty.double(), empty.long(), torch.zeros(0, dtype=torch.int64, device=device))
    # an edge on a batch's border is crossed by cubes of two batches: merged once more
    keys, inverse = torch.unique(torch.cat([part.keys for part in parts]), return_inverse=True)
    vertices = torch.empty(len(keys), 3, dtype=torch.float64, device=device)
    vertices[inverse] = torch.cat([part.positions for part in parts])  # the same value from each batch
    voxels = torch.empty(len(keys), dtype=torch.int64, device=device)
    voxels[inverse] = torch.cat([part.nearest for part in parts])
    offsets = np.cumsum([0] + [len(part.keys) for part in parts[:-1]])
    triangles = torch.cat([inverse[part.triangles + int(offset)] for part, offset in zip(parts, offsets)])
    return SparseMesh(vertices, triangles, voxels)


def _batch_crossings(coords: torch.Tensor, neighbour_rows: torch.Tensor, tsdf: torch.Tensor, observed: torch.Tensor,
                     block: int, tables: _Tables) -> _Crossings | None:
    """A batch of blocks meshed; None when no cube of the batch holds surface."""
    sources = neighbour_rows[:, tables.neighbour]  # [B, patch]: rows
    present = sources >= 0
    flat = torch.where(present, sources * block**3 + tables.local, 0)
    values = tsdf.view(-1)[flat]
    seen = observed.view(-1)[flat] & present
    corner_values, corner_seen = values[:, tables.cube_corners], seen[:, tables.cube_corners]  # [B, block^3, 8]
    case = ((corner_values < 0) * tables.corner_bits).sum(-1)
    surface = corner_seen.all(-1) & (case > 0) & (case < 255)
    in_batch, cube = torch.nonzero(surface, as_tuple=True)
    if not len(in_batch):
        return None
    table = tables.triangles[case[in_batch, cube]]  # [n, T, 3] edges, -1 past a case's triangles
    kept = table[..., 0] >= 0
    # each triangle corner as (its cube among the surface's, its edge)
    surface_cube = torch.arange(len(in_batch), device=tsdf.device)[:, None, None].expand(table.shape)[kept].view(-1)
    edge = table[kept].view(-1)
    ends = tables.cube_corners[cube[surface_cube][:, None], tables.edge_corners[edge]]  # [3F, 2] patch voxels
    block_of = in_batch[surface_cube]  # the corner's block, in the batch
    low_flat, high_flat = flat[block_of, ends[:, 0]], flat[block_of, ends[:, 1]]
    low_value, high_value = values[block_of, ends[:, 0]].double(), values[block_of, ends[:, 1]].double()
    t = low_value / (low_value - high_value)  # where the TSDF crosses 0 between the ends
    axis = tables.edge_axes[edge]
    patch = block + 1
    low_voxel = coords[block_of] * block + torch.stack([ends[:, 0] // patch**2, ends[:, 0] // patch % patch,
                                                       ends[:, 0] % patch], dim=1)
    position = low_voxel.double()
    along = torch.arange(len(axis), device=tsdf.device), axis
    position[along] += t
    low_even = low_voxel[along] % 2 == 0
    nearest = torch.where((t < 0.5) | ((t == 0.5) & low_even), low_flat, high_flat)
    keys, inverse = torch.unique(low_flat * 3 + axis, return_inverse=True)
    positions = torch.empty(len(keys), 3, dtype=torch.float64, device=tsdf.device)
    positions[inverse] = position
    nearest_voxels = torch.empty(len(keys), dtype=torch.int64, device=tsdf.device)
    nearest_voxels[inverse] = nearest
    return _Crossings(keys, positions, nearest_voxels, inverse.view(-1, 3))
