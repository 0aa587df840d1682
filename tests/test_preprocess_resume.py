"""Resuming an interrupted preprocessing run never reuses a shard built from inputs that changed since.

Each shard's key covers its samples, settings, poses, K and the size and mtime of every source file it
reads (``Sequence.frame_files``); a finished shard in the staging folder is reused only while its key holds.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from endoflow.config import Params
from endoflow.data.registry import open_reader
from endoflow.data.shard_format import MANIFEST
from endoflow.data.shards import preprocess_dataset, write_dataset_shards
from endoflow.errors import DataFormatError
from tests.fixtures_native import (
    preprocess_params,
    replace_line,
    repaint_simcol_frame,
    write_endoslam_camera,
    write_endoslam_unitycam,
    write_scenenet,
    write_simcol,
)

SCENE = "SyntheticColon_I"
DAMAGED_TEST_DEPTH = ("SyntheticColon_III", "O1", 4)  # read only by the last test shard (the field of view is
# found from the frames, not the depth maps)


def staged_shards(out_dir: Path) -> set[str]:
    return {p.name for p in (out_dir.parent / f".{out_dir.name}.partial").glob("*.tar")}


def shards_with_targets(out_dir: Path, sequence: str, frames: set[int]) -> set[str]:
    manifest = pq.read_table(out_dir / MANIFEST).to_pandas()
    rows = manifest[(manifest["sequence"] == sequence) & manifest["frame"].isin(frames)]
    return set(rows["shard"])


def assert_same_files(a: Path, b: Path) -> None:
    names = sorted(p.name for p in a.iterdir())
    assert names == sorted(p.name for p in b.iterdir())
    for name in names:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


@pytest.fixture
def interrupted(tmp_path: Path) -> tuple[Path, Path, Params]:
    """A SimCol root (S1 train, S4 val, O1 test; 6 frames, 2 samples per shard) and a preprocessing run of
    it that stopped at a damaged test depth map, after the train, val and first test shards were finished."""
    root = tmp_path / "simcol"
    write_simcol(root, frames=6, size=16)
    scene, name, number = DAMAGED_TEST_DEPTH
    frame = root / scene / f"Frames_{name}" / f"Depth_{number:04d}.png"
    intact = frame.read_bytes()
    frame.write_bytes(intact[: len(intact) // 2])
    params = preprocess_params("simcol", root)
    out_dir = tmp_path / "shards" / "simcol"
    with pytest.raises(DataFormatError, match=frame.name):
        preprocess_dataset("simcol", params, out_dir)
    frame.write_bytes(intact)
    assert not out_dir.exists() and len(staged_shards(out_dir)) == 5
    return root, out_dir, params


def clean_run(root: Path, tmp_path: Path) -> Path:
    """Shards of ``root`` (as it is now) written from scratch, elsewhere."""
    out_dir = tmp_path / "clean" / "simcol"
    preprocess_dataset("simcol", preprocess_params("simcol", root), out_dir)
    return out_dir


def test_a_changed_image_rebuilds_the_shards_built_from_it_and_reuses_the_others(
    interrupted: tuple[Path, Path, Params], tmp_path: Path
) -> None:
    root, out_dir, params = interrupted
    finished = staged_shards(out_dir)
    repaint_simcol_frame(root / SCENE, "S1", 1)
    summary = preprocess_dataset("simcol", params, out_dir)
    read_frame_1 = shards_with_targets(out_dir, "S1", {1, 2})  # frame 1 is cur of target 1, prev of 2
    assert read_frame_1 and read_frame_1 <= finished
    assert summary["shards_reused"] == len(finished - read_frame_1) == 4
    assert_same_files(out_dir, clean_run(root, tmp_path))


def test_a_changed_pose_rebuilds_only_the_shards_that_store_it(
    interrupted: tuple[Path, Path, Params], tmp_path: Path
) -> None:
    root, out_dir, params = interrupted
    finished = staged_shards(out_dir)
    replace_line(root / SCENE / "SavedPosition_S1.txt", 5, "1.5 2.5 3.5")
    summary = preprocess_dataset("simcol", params, out_dir)
    stored_frame_5 = shards_with_targets(out_dir, "S1", {4})  # frame 5 is only next of target 4
    assert summary["shards_reused"] == len(finished - stored_frame_5) == 4
    assert_same_files(out_dir, clean_run(root, tmp_path))


def test_an_unchanged_input_reuses_every_finished_shard(
    interrupted: tuple[Path, Path, Params], tmp_path: Path
) -> None:
    root, out_dir, params = interrupted
    summary = preprocess_dataset("simcol", params, out_dir)
    assert summary["shards_reused"] == 5
    assert_same_files(out_dir, clean_run(root, tmp_path))
    assert [p.name for p in out_dir.parent.iterdir() if p.name.startswith(".")] == []


# --------------------------------------------------------------------- what each reader says it reads
def frame_files_of_every_reader(root: Path) -> dict[str, list[list[str]]]:
    write_simcol(root / "simcol", frames=2, size=8)
    write_endoslam_unitycam(root / "unitycam", frames=2, size=8)
    write_endoslam_camera(root / "camera", frames=2)
    write_scenenet(root / "scenenet", frame_ids=(0, 25))
    params = Params()
    params.data.endoslam.intrinsics = [[30.0, 0.0, 16.0], [0.0, 30.0, 12.0], [0.0, 0.0, 1.0]]
    files = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the camera sheet leaves a frame without a pose
        for folder, dataset in (("simcol", "simcol"), ("unitycam", "endoslam"), ("camera", "endoslam"),
                                ("scenenet", "scenenet")):
            sequence = open_reader(root / folder, dataset, params).sequences()[0]
            files[folder] = [[p.relative_to(root / folder).as_posix() for p in sequence.frame_files(i)]
                             for i in range(len(sequence))]
    return files


def test_every_reader_names_the_files_each_frame_is_decoded_from(tmp_path: Path) -> None:
    o1, colon = "SyntheticColon_III/Frames_O1", "UnityCam/Colon"  # O1 is the first SimCol sequence by name
    assert frame_files_of_every_reader(tmp_path) == {
        "simcol": [[f"{o1}/FrameBuffer_000{i}.png", f"{o1}/Depth_000{i}.png"] for i in range(2)],
        "unitycam": [[f"{colon}/Frames/image_000{i}.png", f"{colon}/Pixelwise Depths/aov_image_000{i}.png"]
                     for i in range(2)],
        "camera": [[f"Cameras/HighCam/Colon-IV/TumorfreeTrajectory_1/Frames/frame_00000{i}.jpg"] for i in range(2)],
        "scenenet": [[f"train/0/7/depth/{n}.png", f"train/0/7/photo/{n}.jpg"] for n in (0, 25)],
    }


def test_a_source_file_gone_since_listing_is_named(tmp_path: Path) -> None:
    root = tmp_path / "simcol"
    write_simcol(root, frames=4, size=8)
    params = preprocess_params("simcol", root)
    sequences = open_reader(root, "simcol", params).sequences()
    sequences[0].frame_files(1)[1].unlink()
    with pytest.raises(DataFormatError, match="Depth_0001.png: source file listed by the reader cannot be read"):
        write_dataset_shards(lambda: sequences, "simcol", params, tmp_path / "out")


def test_a_reader_setting_that_changes_decoded_frames_changes_every_shard_key() -> None:
    from endoflow.data.shard_plan import ShardSpec, encode_settings, shard_keys

    params = Params()
    rescaled = Params()
    rescaled.data.endoslam = rescaled.data.endoslam.replace(depth_full_scale_cm=25.0)  # same files, other depth
    shard = [ShardSpec("test-000000.tar", "test", ())]
    assert (shard_keys(shard, encode_settings("endoslam", params), [])
            != shard_keys(shard, encode_settings("endoslam", rescaled), []))
