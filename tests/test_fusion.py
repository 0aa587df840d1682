"""TSDF fusion's block table (endoflow/reconstruction/fusion.py): keys that round-trip, rows that stay with their
blocks however the table grows, and a surface that does not depend on the order blocks were first seen in. The
fused surface against ground truth is tested through reconstruct (tests/test_reconstruct.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from endoflow.config import ConfigError
from endoflow.reconstruction.fusion import TSDFVolume, pack_block_keys, unpack_block_keys

LIMIT = 1 << 20  # blocks from the origin a key can name


def test_block_keys_round_trip_and_sort_as_their_coordinates() -> None:
    generator = torch.Generator().manual_seed(0)
    coords = torch.randint(-LIMIT + 1, LIMIT, (500, 3), generator=generator)
    coords = torch.cat([coords, torch.tensor([[0, 0, 0], [-1, -1, -1], [LIMIT - 1] * 3, [-LIMIT + 1] * 3])])
    keys = pack_block_keys(coords)
    assert torch.equal(unpack_block_keys(keys), coords)
    lexicographic = sorted(range(len(coords)), key=lambda i: tuple(coords[i].tolist()))
    assert torch.equal(torch.argsort(keys), torch.tensor(lexicographic))


def test_a_block_beyond_the_keys_range_is_refused_with_the_option_that_helps() -> None:
    for axis in range(3):
        for side in (LIMIT, -LIMIT):
            beyond = torch.zeros(1, 3, dtype=torch.int64)
            beyond[0, axis] = side
            with pytest.raises(ValueError, match="--voxel-cm"):
                pack_block_keys(beyond)


def test_each_block_keeps_the_row_it_was_given_first_however_the_table_grows() -> None:
    volume = TSDFVolume(0.1, 0.4)
    generator = torch.Generator().manual_seed(1)
    given: dict[int, int] = {}
    for _ in range(12):  # batches that overlap earlier ones, in the sorted unique form integrate passes
        keys = torch.unique(pack_block_keys(torch.randint(-40, 40, (200, 3), generator=generator)))
        rows = volume._rows_of(keys)
        for key, row in zip(keys.tolist(), rows.tolist()):
            assert given.setdefault(key, row) == row
    assert volume.block_count == len(given) == len(set(given.values()))
    assert torch.equal(volume._keys, torch.sort(volume._keys).values)
    assert sorted(given.values()) == list(range(len(given)))


def plane_frames(size: int = 48) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    K = np.array([[size * 0.6, 0, size / 2], [0, size * 0.6, size / 2], [0, 0, 1.0]])
    v, u = np.mgrid[0:size, 0:size]
    rgb = np.stack([u * 5 % 256, v * 5 % 256, (u + v) % 256], axis=-1).astype(np.uint8)
    frames = []
    for step in range(3):
        T_world_cam = np.eye(4)
        T_world_cam[:3, 3] = [0.2 * step, 0.1 * step, 0.0]
        depth = np.full((size, size), 5.0, np.float32)  # the plane z = 5 cm seen straight on
        frames.append((depth, rgb, K, T_world_cam))
    return frames


def test_the_surface_does_not_depend_on_the_order_blocks_were_first_seen_in() -> None:
    meshes = []
    for order in ([0, 1, 2], [2, 1, 0]):
        volume = TSDFVolume(0.05, 0.2)
        frames = plane_frames()
        for index in order:
            volume.integrate(*frames[index])
        meshes.append(volume.extract_mesh())
    forwards, backwards = meshes
    assert len(forwards.vertices) > 1000
    assert np.allclose(np.sort(forwards.vertices, axis=0), np.sort(backwards.vertices, axis=0), atol=1e-5)
    assert np.mean(np.abs(forwards.vertices[:, 2] - 5.0) < 0.05) > 0.9  # the plane, within a voxel (but its rim)


def test_unknown_depth_fuses_nothing() -> None:
    volume = TSDFVolume(0.05, 0.2)
    depth, rgb, K, T = plane_frames()[0]
    unknown = np.zeros_like(depth)
    unknown[0, :3] = np.nan
    volume.integrate(unknown, rgb, K, T)
    assert volume.block_count == 0 and len(volume.extract_mesh().vertices) == 0


def wavy_frames(count: int = 4, height: int = 40, width: int = 56) -> list[tuple[np.ndarray, ...]]:
    """A wavy wall seen from a camera that moves and turns, in frames with holes (zeros, NaN) and a K whose
    centre and focal lengths are not round in float32."""
    generator = np.random.default_rng(3)
    K = np.array([[41.37, 0, width / 2 - 0.3], [0, 43.91, height / 2 + 0.17], [0, 0, 1.0]])
    v, u = np.mgrid[0:height, 0:width]
    frames = []
    for step in range(count):
        depth = (3.0 + 0.4 * np.sin(u / 5.0 + step) + 0.3 * np.cos(v / 7.0) + 0.02 * u).astype(np.float32)
        depth[generator.random(depth.shape) < 0.05] = 0.0
        depth[:3, :4] = np.nan
        rgb = generator.integers(0, 256, (height, width, 3), dtype=np.uint8)
        angle = 0.05 * step
        T_world_cam = np.eye(4)
        T_world_cam[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
        T_world_cam[:3, 3] = [0.13 * step, -0.07 * step, 0.21 * step]
        frames.append((depth, rgb, K, T_world_cam))
    return frames


def test_the_compiled_loops_fuse_the_volume_of_the_tensor_code_to_the_bit() -> None:
    volumes = [TSDFVolume(0.031, 0.124, compiled=compiled) for compiled in (True, False)]
    for frame in wavy_frames():
        for volume in volumes:
            volume.integrate(*frame)
    loops, tensors = volumes
    assert loops._compiled and not tensors._compiled
    assert loops.block_count == tensors.block_count > 100
    for name in ("_keys", "_rows", "_tsdf", "_weight", "_colour"):
        assert torch.equal(getattr(loops, name), getattr(tensors, name)), name
    assert (loops._weight > 1).any()  # frames overlapped: averaging, not only first sightings, was compared


def test_the_compiled_loops_name_each_block_the_tensor_code_touches_and_few_twice() -> None:
    from endoflow.reconstruction import fusion, tsdf_loops

    volumes = [TSDFVolume(0.031, 0.124, compiled=compiled) for compiled in (True, False)]
    for depth, _, K, T_world_cam in wavy_frames():
        depth = np.where(np.isfinite(depth), depth, 0).astype(np.float32)
        touched = [volume._touched_keys(torch.from_numpy(depth), K, T_world_cam) for volume in volumes]
        assert torch.equal(*touched) and len(touched[0]) > 50
        block_cm = fusion.BLOCK * volumes[0].voxel_cm
        offsets = np.append(np.arange(-0.124, 0.124 + block_cm, block_cm / 2), 0.124)
        named, _ = tsdf_loops.ray_block_keys(depth, K, T_world_cam, offsets, block_cm, fusion._KEY_BITS)
        assert torch.equal(torch.unique(torch.from_numpy(named)), touched[0])
        # of some 10,000 ray points, in about 1,000 blocks: a key is written again only where another took its slot
        assert len(named) < 1.2 * len(touched[0]) < 0.12 * (depth > 0).sum() * len(offsets)


@pytest.mark.parametrize("compiled", [True, False], ids=["loops", "tensors"])
def test_a_frame_beyond_the_keys_range_is_refused_with_the_option_that_helps(compiled: bool) -> None:
    volume = TSDFVolume(0.01, 0.04, compiled=compiled)
    depth, rgb, K, T_world_cam = plane_frames()[0]
    T_world_cam = T_world_cam.copy()
    T_world_cam[0, 3] = 1e5  # 1 km along x: 1.25 million blocks of 0.08 cm
    with pytest.raises(ConfigError, match="--voxel-cm"):  # the command line prints it as an error
        volume.integrate(depth, rgb, K, T_world_cam)


def test_the_chunked_mesh_is_the_mesh_of_the_whole_grid_at_once() -> None:
    from skimage.measure import marching_cubes

    from endoflow.reconstruction.fusion import BLOCK, CHUNK_BLOCKS, observed_cubes

    volume = TSDFVolume(0.02, 0.08)  # 0.16 cm blocks, 1.28 cm chunks: the wall's view crosses many chunk seams
    for frame in wavy_frames():
        volume.integrate(*frame)
    coords = unpack_block_keys(volume._keys).numpy()
    low = coords.min(axis=0)
    shape = tuple((coords.max(axis=0) - low + 1) * BLOCK)
    tsdf, weight = np.ones(shape, np.float32), np.zeros(shape, np.float32)
    for coord, row in zip(coords - low, volume._rows.tolist()):  # block by block: the plainest reading
        region = tuple(slice(c * BLOCK, (c + 1) * BLOCK) for c in coord)
        tsdf[region] = volume._tsdf[row].reshape(BLOCK, BLOCK, BLOCK).numpy()
        weight[region] = volume._weight[row].reshape(BLOCK, BLOCK, BLOCK).numpy()
    vertices, _, _, _ = marching_cubes(tsdf, level=0.0, mask=observed_cubes(weight > 0))
    whole = (vertices + low * BLOCK + 0.5) * volume.voxel_cm
    chunked = volume.extract_mesh().vertices
    assert len(np.unique(coords // CHUNK_BLOCKS, axis=0)) > 8
    assert len(whole) > 1000
    for these, those in ((whole, chunked), (chunked, whole)):  # the same points (seams' twice), up to rounding
        assert cKDTree(those).query(these)[0].max() < 0.01 * volume.voxel_cm


def test_each_vertex_takes_the_colour_of_its_nearest_voxel() -> None:
    from endoflow.reconstruction.fusion import BLOCK

    volume = TSDFVolume(0.02, 0.08)
    for frame in wavy_frames():
        volume.integrate(*frame)
    mesh = volume.extract_mesh()
    row_of = dict(zip(map(tuple, unpack_block_keys(volume._keys).tolist()), volume._rows.tolist()))
    voxels = mesh.vertices / volume.voxel_cm - 0.5  # voxel centres sit at (index + 0.5) voxels
    clear = np.all(np.abs(voxels - np.floor(voxels) - 0.5) > 1e-3, axis=1)  # not halfway: one nearest voxel
    nearest = np.round(voxels[clear]).astype(np.int64)
    expected = []
    for voxel in nearest:  # the plainest reading: the block, its row, the voxel's place in it
        block = tuple(np.floor_divide(voxel, BLOCK).tolist())
        i, j, k = voxel - np.array(block) * BLOCK
        expected.append(volume._colour[row_of[block], (i * BLOCK + j) * BLOCK + k].numpy())
    expected = np.clip(np.round(np.array(expected)), 0, 255).astype(np.uint8)
    assert clear.mean() > 0.9 and len(np.unique(expected, axis=0)) > 100  # the frames' random colours, mixed
    np.testing.assert_array_equal(mesh.colours[clear], expected)


def test_no_face_reaches_a_voxel_never_observed() -> None:
    tsdf = np.ones((4, 4, 4), np.float32)
    tsdf[1, 1, 1] = -1.0  # behind the surface: a crossing on each edge from it
    observed = np.zeros((4, 4, 4), bool)
    observed[1:, 1:, 1:] = True  # the 8 cubes around voxel (1, 1, 1) reach unobserved voxels, but one
    from skimage.measure import marching_cubes

    from endoflow.reconstruction.fusion import observed_cubes

    vertices, _, _, _ = marching_cubes(tsdf, level=0.0, mask=observed_cubes(observed))
    assert len(vertices) == 3 and (vertices >= 1).all()  # one corner of the one cube from (1, 1, 1) to (2, 2, 2)


@pytest.mark.parametrize("block", [-LIMIT, -LIMIT + 1, LIMIT - 1, LIMIT])
def test_the_compiled_loops_refuse_the_blocks_the_key_packing_refuses(block: int) -> None:
    from endoflow.reconstruction import fusion, tsdf_loops

    T_world_cam = np.eye(4)
    T_world_cam[0, 3] = block + 0.5  # the one ray point (x = 0 in the camera) lies inside block `block` of 1 cm
    K = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1]])
    _, beyond = tsdf_loops.ray_block_keys(np.ones((1, 1), np.float32), K, T_world_cam, np.zeros(1), 1.0,
                                          fusion._KEY_BITS)
    refused = False
    try:
        pack_block_keys(torch.tensor([[block, 0, 1]]))
    except ValueError:
        refused = True
    assert beyond == refused == (abs(block) >= LIMIT)


@pytest.mark.parametrize("compiled", [True, False], ids=["loops", "tensors"])
def test_a_depth_map_laid_out_column_first_fuses_as_its_copy(compiled: bool) -> None:
    depth, rgb, K, T_world_cam = wavy_frames(1)[0]
    volumes = [TSDFVolume(0.031, 0.124, compiled=compiled) for _ in range(2)]
    volumes[0].integrate(np.asfortranarray(depth), rgb, K, T_world_cam)
    volumes[1].integrate(depth, rgb, K, T_world_cam)
    assert volumes[0].block_count == volumes[1].block_count > 0
    assert torch.equal(volumes[0]._tsdf, volumes[1]._tsdf)


@pytest.mark.parametrize("compiled", [True, False], ids=["loops", "tensors"])
def test_voxels_in_the_cameras_plane_are_left_out_as_those_behind_it(compiled: bool) -> None:
    """A camera half a voxel above the origin has a layer of voxel centres exactly in its plane (z = 0): the loops
    once divided by that 0 and raised on a real video."""
    voxel_cm, trunc_cm = 0.25, 1.0  # a truncation that reaches back past the camera's plane
    depth = np.full((8, 8), 0.25, np.float32)
    K = np.array([[4.0, 0, 4.0], [0, 4.0, 4.0], [0, 0, 1]])
    T_world_cam = np.eye(4)
    T_world_cam[2, 3] = 0.5 * voxel_cm
    volume = TSDFVolume(voxel_cm, trunc_cm, compiled=compiled)
    volume.integrate(depth, np.zeros((8, 8, 3), np.uint8), K, T_world_cam)
    reference = TSDFVolume(voxel_cm, trunc_cm, compiled=not compiled)
    reference.integrate(depth, np.zeros((8, 8, 3), np.uint8), K, T_world_cam)
    assert volume.block_count == reference.block_count > 0
    assert torch.equal(volume._tsdf, reference._tsdf) and torch.equal(volume._weight, reference._weight)
    assert (volume._weight > 0).any()
