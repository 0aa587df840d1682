"""SceneNet RGB-D reader: ray length in mm -> z-depth in cm, the documented camera, numeric frame order."""

from __future__ import annotations


import numpy as np
import pytest

from endoflow.config import SceneNetConfig
from endoflow.data.imageio import write_png
from endoflow.data.scenenet import SceneNetReader, scenenet_intrinsics
from endoflow.errors import DataFormatError
from tests.fixtures_native import write_scenenet


def test_documented_intrinsics_at_320x240_in_our_pixel_centre_convention():
    K = scenenet_intrinsics(240, 320)
    np.testing.assert_allclose(K, [[277.128, 0, 159.5], [0, 289.706, 119.5], [0, 0, 1]], atol=1e-3)


def test_ray_length_becomes_z_depth_on_a_known_plane(tmp_path):
    truth = write_scenenet(tmp_path, size=(24, 32))
    (sequence,) = SceneNetReader(tmp_path, SceneNetConfig()).sequences()
    np.testing.assert_allclose(sequence.K, truth.K)
    for k in range(len(sequence)):
        depth = sequence.load_depth(k)
        assert depth.dtype == np.float32 and depth.shape == (24, 32)
        np.testing.assert_allclose(depth, truth.depth_cm[k], rtol=1e-6)
        plane_cm = 150.0 + 40.0 * k
        readings = depth[depth > 0]
        assert np.abs(readings - plane_cm).max() <= 0.05  # mm rounding of the stored ray length
        assert depth[0, 0] == 0  # no reading stays no reading


def test_frames_in_numeric_order_split_from_folder_and_no_poses(tmp_path):
    truth = write_scenenet(tmp_path, split="val", part="3", trajectory="12", frame_ids=(100, 0, 25, 50))
    (sequence,) = SceneNetReader(tmp_path, SceneNetConfig()).sequences()
    assert (sequence.name, sequence.split, sequence.group) == ("val/3/12", "val", "3")
    assert sequence.frame_ids == [0, 25, 50, 100]
    assert sequence.poses is None and sequence.pose(0) is None
    by_id = dict(zip(truth.frame_ids, truth.depth_cm))
    np.testing.assert_allclose(sequence.load_depth(3), by_id[100], rtol=1e-6)
    rgb = sequence.load_rgb(1)
    assert rgb.shape == (24, 32, 3) and np.abs(rgb.astype(int) - truth.rgb[truth.frame_ids.index(25)]).max() <= 4


def test_trajectories_sorted_and_capped_by_params(tmp_path):
    write_scenenet(tmp_path, trajectory="10")
    write_scenenet(tmp_path, trajectory="9", photos=False)
    write_scenenet(tmp_path, split="val", part="0", trajectory="1")
    sequences = SceneNetReader(tmp_path, SceneNetConfig().replace(max_frames_per_trajectory=2)).sequences()
    assert [s.name for s in sequences] == ["train/0/9", "train/0/10", "val/0/1"]
    assert [s.frame_ids for s in sequences] == [[0, 25]] * 3
    assert sequences[0].load_rgb is None and sequences[1].load_rgb is not None


def test_depth_of_wrong_bit_depth(tmp_path):
    write_scenenet(tmp_path)
    depth = tmp_path / "train" / "0" / "7" / "depth" / "25.png"
    write_png(depth, np.zeros((24, 32, 3), np.uint8))
    (sequence,) = SceneNetReader(tmp_path, SceneNetConfig()).sequences()
    with pytest.raises(DataFormatError, match="16-bit single-channel PNG, found uint8 with 3 channel") as info:
        sequence.load_depth(1)
    assert info.value.path == depth


def test_missing_photo(tmp_path):
    write_scenenet(tmp_path)
    photo = tmp_path / "train" / "0" / "7" / "photo" / "50.jpg"
    photo.unlink()
    with pytest.raises(DataFormatError, match="missing image: photo for depth/50.png") as info:
        SceneNetReader(tmp_path, SceneNetConfig()).sequences()
    assert info.value.path == photo


def test_trajectory_without_depth_folder(tmp_path):
    write_scenenet(tmp_path)
    (tmp_path / "train" / "0" / "8").mkdir()
    with pytest.raises(DataFormatError, match="depth folder not found") as info:
        SceneNetReader(tmp_path, SceneNetConfig()).sequences()
    assert info.value.path == tmp_path / "train" / "0" / "8" / "depth"
