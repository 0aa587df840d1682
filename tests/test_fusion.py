"""TSDF fusion's block table (endoflow/reconstruction/fusion.py): keys that round-trip, rows that stay with their
blocks however the table grows, and a surface that does not depend on the order blocks were first seen in. The
fused surface against ground truth is tested through reconstruct (tests/test_reconstruct.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

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
