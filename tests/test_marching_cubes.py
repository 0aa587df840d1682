"""The volume's own marching cubes (endoflow/reconstruction/marching_cubes.py), which meshes a volume on a GPU: a
closed, consistently wound surface in every one of the 256 corner cases, scikit-image's vertices, normals out of
the tissue, nothing where a voxel was never observed, and the same mesh however the blocks are batched. It runs on
a CPU too, which is where these tests run it."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from endoflow.reconstruction import marching_cubes as mc
from endoflow.reconstruction.fusion import BLOCK, SurfaceMesh, TSDFVolume, pack_block_keys, unpack_block_keys
from tests.test_fusion import wavy_frames

VOXEL_CM = 0.1


def volume_of(values: np.ndarray, observed: np.ndarray | None = None, seed: int = 0) -> TSDFVolume:
    """A volume holding a dense grid (``values``, a multiple of BLOCK on each axis, voxel (0, 0, 0) at block
    (0, 0, 0)), every block allocated, voxels observed where ``observed`` (default: all), random colours. Blocks are
    allocated in a shuffled order, so that a block's row is not its place in the key table."""
    observed = np.ones(values.shape, bool) if observed is None else observed
    volume = TSDFVolume(VOXEL_CM, 4 * VOXEL_CM)
    blocks = [np.arange(size // BLOCK) for size in values.shape]
    coords = torch.tensor(list(itertools.product(*blocks)))
    generator = torch.Generator().manual_seed(seed)
    for coord in coords[torch.randperm(len(coords), generator=generator)]:
        row = int(volume._rows_of(pack_block_keys(coord[None])))
        i, j, k = (int(c) * BLOCK for c in coord)
        region = (slice(i, i + BLOCK), slice(j, j + BLOCK), slice(k, k + BLOCK))
        volume._tsdf[row] = torch.from_numpy(values[region].reshape(-1).astype(np.float32))
        volume._weight[row] = torch.from_numpy(observed[region].reshape(-1).astype(np.float32))
    volume._colour[:volume.block_count] = torch.randint(0, 256, volume._colour[:volume.block_count].shape,
                                                        generator=generator).float()
    return volume


def closed_and_consistently_wound(mesh: SurfaceMesh) -> None:
    """Every directed edge of a triangle is met once, reversed, by another: a closed surface with no cracks, no
    repeated faces and one orientation throughout."""
    t = mesh.triangles
    directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    forwards = {tuple(edge) for edge in directed.tolist()}
    assert len(forwards) == len(directed), "an edge is wound the same way by two triangles"
    assert forwards == {(b, a) for a, b in forwards}, "an edge is met by one triangle only"


def face_normals(mesh: SurfaceMesh) -> np.ndarray:
    v, t = mesh.vertices, mesh.triangles
    return np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])


def scikit_edge_vertices(values: np.ndarray, observed: np.ndarray | None = None) -> np.ndarray:
    """scikit-image's vertices on cube edges (in world cm, as the volume places them), leaving out the points
    its Lewiner variant adds inside some ambiguous cubes."""
    from skimage.measure import marching_cubes

    from endoflow.reconstruction.fusion import observed_cubes

    mask = observed_cubes(np.ones(values.shape, bool) if observed is None else observed)
    vertices, _, _, _ = marching_cubes(values.astype(np.float32), level=0.0, mask=mask)
    on_edge = (np.abs(vertices - np.round(vertices)) > 1e-6).sum(1) <= 1
    return (vertices[on_edge] + 0.5) * VOXEL_CM


def test_each_case_crosses_exactly_its_edges_between_inside_and_outside() -> None:
    for case in range(256):
        inside = [bool(case >> c & 1) for c in range(8)]
        crossing = {e for e, (corner, axis) in enumerate(mc._EDGES)
                    if inside[corner] != inside[corner + mc.CORNER_WEIGHTS[axis]]}
        used = set(mc.TRIANGLES[case][mc.TRIANGLES[case, :, 0] >= 0].view(-1).tolist())
        assert used == crossing, case
    assert (mc.TRIANGLES[0] < 0).all() and (mc.TRIANGLES[255] < 0).all()


def test_a_sphere_is_closed_wound_outwards_and_its_vertices_are_scikit_images() -> None:
    grid = np.indices((24, 24, 24)).astype(float) - 11.3
    values = np.clip((np.sqrt((grid**2).sum(0)) - 7.0) / 4.0, -1.0, 1.0)  # a TSDF: negative inside the tissue
    mesh = volume_of(values).extract_mesh_on_device()
    closed_and_consistently_wound(mesh)
    chi = len(mesh.vertices) - len(mesh.triangles) * 3 // 2 + len(mesh.triangles)
    assert chi == 2  # V - E + F of a sphere
    centre = (11.3 + 0.5) * VOXEL_CM
    for wound in (mesh, volume_of(values).extract_mesh_on_host()):  # ours as scikit-image's: a CPU's and a GPU's
        outward = wound.vertices[wound.triangles].mean(1) - centre
        assert (np.einsum("ij,ij->i", face_normals(wound), outward) > 0).all()  # towards increasing TSDF
    expected = scikit_edge_vertices(values)
    assert len(mesh.vertices) == len(expected) > 500
    assert cKDTree(expected).query(mesh.vertices)[0].max() < 1e-5 * VOXEL_CM


def test_noise_meets_every_ambiguous_case_and_the_surface_stays_closed() -> None:
    values = np.random.default_rng(0).uniform(-1, 1, (16, 16, 24))
    values[[0, -1]], values[:, [0, -1]], values[:, :, [0, -1]] = 1.0, 1.0, 1.0  # outside at the border: closed
    volume = volume_of(values)
    assert not torch.equal(volume._rows, torch.arange(volume.block_count))  # rows are not key places
    mesh = volume.extract_mesh_on_device()
    closed_and_consistently_wound(mesh)
    corners = np.stack([values[i:i + 15, j:j + 15, k:k + 23] < 0 for i, j, k in mc.CORNERS], -1)
    cases = set((corners * (1 << np.arange(8))).sum(-1).ravel().tolist())
    assert len(cases) == 256  # every case met
    expected = scikit_edge_vertices(values)
    assert len(mesh.vertices) == len(expected)
    assert cKDTree(expected).query(mesh.vertices)[0].max() < 1e-5 * VOXEL_CM


def test_no_face_reaches_a_voxel_never_observed() -> None:
    values = np.ones((8, 8, 8))
    values[1, 1, 1] = -1.0  # behind the surface: a crossing on each edge from it
    observed = np.zeros((8, 8, 8), bool)
    observed[1:, 1:, 1:] = True  # of the 8 cubes around voxel (1, 1, 1) only the one beyond it is all observed
    mesh = volume_of(values, observed).extract_mesh_on_device()
    assert len(mesh.vertices) == 3 and len(mesh.triangles) == 1
    assert (mesh.vertices / VOXEL_CM - 0.5 >= 1).all()


def test_a_volume_without_surface_meshes_to_nothing() -> None:
    for values in (np.ones((8, 8, 16)), -np.ones((8, 8, 16))):  # all in front of the surface, all behind it
        mesh = volume_of(values).extract_mesh_on_device()
        assert mesh.vertices.shape == (0, 3) and mesh.triangles.shape == (0, 3) and mesh.colours.shape == (0, 3)
    empty = TSDFVolume(VOXEL_CM, 4 * VOXEL_CM).extract_mesh_on_device()
    assert len(empty.vertices) == len(empty.triangles) == 0


def test_the_mesh_does_not_depend_on_how_the_blocks_are_batched(monkeypatch: pytest.MonkeyPatch) -> None:
    values = np.random.default_rng(1).uniform(-1, 1, (24, 16, 16))
    values[[0, -1]], values[:, [0, -1]], values[:, :, [0, -1]] = 1.0, 1.0, 1.0
    volume = volume_of(values)
    whole = volume.extract_mesh_on_device()
    monkeypatch.setattr(mc, "BLOCKS_PER_BATCH", 5)  # 18 blocks: four batches, cubes meeting across them
    batched = volume.extract_mesh_on_device()
    for name in ("vertices", "triangles", "colours"):
        np.testing.assert_array_equal(getattr(batched, name), getattr(whole, name))
    closed_and_consistently_wound(batched)  # a triangle is its three corners wherever their batches put them


def test_a_fused_volume_meshes_as_scikit_image_meshes_it_and_takes_the_same_colours() -> None:
    volume = TSDFVolume(0.02, 0.08)
    for frame in wavy_frames():
        volume.integrate(*frame)
    on_device, chunked = volume.extract_mesh_on_device(), volume.extract_mesh_on_host()
    assert len(on_device.vertices) > 100_000
    distance, nearest = cKDTree(chunked.vertices).query(on_device.vertices)
    assert distance.max() < 1e-4 * volume.voxel_cm  # each vertex is one of scikit-image's
    # scikit-image's own are those and the points its Lewiner variant adds inside a few ambiguous cubes
    assert len(np.unique(nearest)) == len(on_device.vertices) > 0.99 * len(np.unique(chunked.vertices, axis=0))
    np.testing.assert_array_equal(on_device.colours, chunked.colours[nearest])
    area = [np.linalg.norm(face_normals(mesh), axis=1).sum() / 2 for mesh in (on_device, chunked)]
    assert area[0] == pytest.approx(area[1], rel=0.005)


def test_a_vertex_halfway_between_two_voxels_takes_the_colour_scikit_images_takes() -> None:
    """A TSDF clamped to -1 and +1 on either side of a step puts vertices exactly halfway: both extractions then take
    the voxel numpy's rounding takes (the even one)."""
    values = np.where(np.random.default_rng(2).random((16, 16, 16)) < 0.3, -1.0, 1.0)
    values[[0, -1]], values[:, [0, -1]], values[:, :, [0, -1]] = 1.0, 1.0, 1.0
    volume = volume_of(values, seed=2)
    on_device, on_host = volume.extract_mesh_on_device(), volume.extract_mesh_on_host()
    distance, nearest = cKDTree(on_host.vertices).query(on_device.vertices)
    voxels = on_device.vertices / VOXEL_CM - 0.5
    assert distance.max() < 1e-9 and np.all(np.abs(np.abs(voxels - np.round(voxels)).max(1) - 0.5) < 1e-6)
    np.testing.assert_array_equal(on_device.colours, on_host.colours[nearest])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_a_gpu_meshes_a_fused_volume_as_a_cpu_does_with_the_same_code() -> None:
    volumes = [TSDFVolume(0.02, 0.08, device) for device in ("cpu", "cuda")]
    for frame in wavy_frames():
        for volume in volumes:
            volume.integrate(*frame)
    on_cpu, on_gpu = (volume.extract_mesh_on_device() for volume in volumes)
    assert len(on_cpu.vertices) > 100_000
    np.testing.assert_allclose(on_gpu.vertices, on_cpu.vertices, rtol=0, atol=1e-6 * 0.02)
    np.testing.assert_array_equal(on_gpu.triangles, on_cpu.triangles)
    np.testing.assert_array_equal(on_gpu.colours, on_cpu.colours)


def test_blocks_at_the_end_of_the_key_range_have_no_neighbour_beyond_it() -> None:
    """A key's y field at its largest plus one carries into x: the key after block (0, 2^20 - 1, 0) on y is not
    that of block (1, -2^20 + 1, 0), the nearest a key can name, nor of any block."""
    half = 1 << 20
    volume = TSDFVolume(VOXEL_CM, 4 * VOXEL_CM)
    coords = torch.tensor([[0, half - 1, 0], [1, -half + 1, 0], [0, half - 1, 1], [half - 1, half - 1, half - 1]])
    volume._rows_of(torch.sort(pack_block_keys(coords)).values)
    rows = dict(zip(map(tuple, coords.tolist()), volume._rows_of(pack_block_keys(coords)).tolist()))
    neighbours = volume._neighbour_rows(unpack_block_keys(volume._keys))
    first = int(torch.nonzero(volume._rows == rows[(0, half - 1, 0)]))
    assert neighbours[first].tolist() == [rows[(0, half - 1, 0)], rows[(0, half - 1, 1)], -1, -1, -1, -1, -1, -1]
    last = int(torch.nonzero(volume._rows == rows[(half - 1,) * 3]))
    assert neighbours[last].tolist() == [rows[(half - 1,) * 3]] + [-1] * 7
