"""Preprocessing into WebDataset shards: sample schema, exact K and depth, manifest, atomic resumable runs.

The synthetic source paints each native pixel with its own coordinates (red = 3u, green = 4v), so a
stored pixel's colour says which native point it shows: the stored K must send both along the same ray.
"""

from __future__ import annotations

import json
import os
import tarfile
import threading
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import cv2
import fsspec
import numpy as np
import pyarrow.parquet as pq
import pytest
import webdataset as wds

from endoflow.config import Params
from endoflow.data.base import Sequence
from endoflow.data.frame_encoding import stored_intrinsics
from endoflow.data.shard_engines import ShardProgress, check_shards_arrived, pool_context
from endoflow.data.shard_plan import DEPTH_UNIT_CM
from endoflow.data.shard_writer import ShardResult
from endoflow.data.shards import preprocess_dataset, write_dataset_shards
from endoflow.data.shard_format import MANIFEST, SHARD_TABLE_KEY, ShardEntry, shard_digests
from endoflow.errors import DataFormatError
from tests.module_temp import ModuleTemp
from tests.samples import SIMCOL_SAMPLE

NATIVE_K = np.array([[40.0, 0.0, 31.0], [0.0, 42.0, 22.5], [0.0, 0.0, 1.0]])
SPLIT_OF = {"S1": "train", "S2": "train", "S4": "val", "S5": "test"}
SAMPLE_FILES = {"prev.png", "cur.png", "next.png", "depth.png", "meta.json", "valid.png"}


def native_rgb(height: int, width: int, position: int) -> np.ndarray:
    v, u = np.mgrid[0:height, 0:width]
    blue = np.full_like(u, (40 * position) % 256)
    return np.stack([3 * u, 4 * v, blue], axis=-1).astype(np.uint8)


def native_depth(height: int, width: int, position: int) -> np.ndarray:
    v, u = np.mgrid[0:height, 0:width]
    depth = (5.0 + 0.013 * u + 0.021 * v + 0.5 * position).astype(np.float32)
    depth[:4, :] = 0.0  # no reading
    depth[4:6, :] = 70.0  # beyond the colon encoding's 65.535 cm
    return depth


def native_pose(position: int) -> np.ndarray:
    angle = 0.05 * position
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    pose[:3, 3] = [0.1 * position, -0.05 * position, 0.2 * position]
    return pose


@dataclass(frozen=True)
class SyntheticSource:
    """Picklable sequence source.

    While the file ``broken`` exists, loading frame 3 of S5 raises (``failure="error"``) or ends the
    process at once, as an out-of-memory kill would (``failure="crash"``).
    """

    dataset: str = "simcol"
    frames: int = 6
    height: int = 48
    width: int = 64
    broken: Optional[str] = None
    failure: str = "error"

    def __call__(self) -> list[Sequence]:
        return [self.sequence(name, split) for name, split in SPLIT_OF.items()]

    def sequence(self, name: str, split: str) -> Sequence:
        height, width = self.height, self.width

        def load_rgb(i: int) -> np.ndarray:
            if self.broken and Path(self.broken).exists() and name == "S5" and i == 3:
                if self.failure == "crash":
                    os._exit(1)
                raise DataFormatError(f"{name}/{i}.png", "unreadable image")
            return native_rgb(height, width, i)

        return Sequence(
            dataset=self.dataset,
            name=name,
            split=split,
            K=NATIVE_K,
            image_size=(height, width),
            frame_ids=[10 + 2 * i for i in range(self.frames)],
            poses=np.stack([native_pose(i) for i in range(self.frames)]),
            load_rgb=None if self.dataset == "scenenet" else load_rgb,
            load_depth=lambda i: native_depth(height, width, i),
            group=f"group_{name[0]}",
        )


def small_params(workers: int = 1, size: int = 32) -> Params:
    params = Params()
    params.data.size = size
    params.preprocess = params.preprocess.replace(workers=workers, samples_per_shard=3, shard_multiple=2)
    return params


def read_tar(path: Path) -> dict[str, dict[str, bytes]]:
    """``{key: {extension: bytes}}`` in tar order (keys end at the first dot, as WebDataset splits them)."""
    samples: dict[str, dict[str, bytes]] = {}
    with tarfile.open(path) as tar:
        for member in tar.getmembers():
            key, extension = member.name.split(".", 1)
            samples.setdefault(key, {})[extension] = tar.extractfile(member).read()
    return samples


def decode_png(data: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB) if image.ndim == 3 else image


def all_samples(out_dir: Path) -> dict[str, dict[str, bytes]]:
    samples = {}
    for shard in sorted(out_dir.glob("*.tar")):
        samples.update(read_tar(shard))
    return samples


@pytest.fixture(scope="module")
def shards(module_tmp: ModuleTemp) -> tuple[Path, dict]:
    out_dir = module_tmp("shards") / "simcol"
    summary = write_dataset_shards(SyntheticSource(), "simcol", small_params(), out_dir)
    return out_dir, summary


def test_every_sample_has_the_schema_and_the_source_poses(shards: tuple[Path, dict]) -> None:
    out_dir, summary = shards
    samples = all_samples(out_dir)
    assert len(samples) == 4 * (6 - 2) == sum(summary["samples"].values())
    for key, files in samples.items():
        assert set(files) == SAMPLE_FILES, key
        meta = json.loads(files["meta.json"])
        position = (meta["frame"] - 10) // 2
        assert key == f"simcol-{meta['sequence']}-{meta['frame']:06d}"
        assert meta["split"] == SPLIT_OF[meta["sequence"]] and meta["group"] == f"group_{meta['sequence'][0]}"
        assert meta["frame_ids"] == {"prev": meta["frame"] - 2, "cur": meta["frame"], "next": meta["frame"] + 2}
        assert meta["native_size"] == [48, 64] and meta["depth_unit"] == DEPTH_UNIT_CM["simcol"]
        for name, shift in (("prev", -1), ("cur", 0), ("next", 1)):
            image = decode_png(files[f"{name}.png"])
            assert image.dtype == np.uint8 and image.shape == (32, 32, 3)
            assert np.all(image[..., 2] == (40 * (position + shift)) % 256)
            np.testing.assert_allclose(meta["T_world_cam"][name], native_pose(position + shift), atol=1e-12)
        depth = decode_png(files["depth.png"])
        assert depth.dtype == np.uint16 and depth.shape == (32, 32)
        valid = decode_png(files["valid.png"])  # frames without a black border: all in view
        assert valid.dtype == np.uint8 and valid.shape == (32, 32) and (valid == 255).all()


def test_stored_k_sends_each_pixel_along_the_ray_of_the_native_point_it_shows(shards: tuple[Path, dict]) -> None:
    out_dir, _ = shards
    files = next(iter(all_samples(out_dir).values()))
    K = np.array(json.loads(files["meta.json"])["K"])
    image = decode_png(files["cur.png"]).astype(np.float64)
    native_u, native_v = image[..., 0] / 3.0, image[..., 1] / 4.0
    v, u = np.mgrid[0:32, 0:32]
    stored_rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    native_rays = np.linalg.inv(NATIVE_K) @ np.stack([native_u.ravel(), native_v.ravel(), np.ones(u.size)])
    # colour quantisation: a native coordinate is known to within 1/6 pixel
    np.testing.assert_allclose(stored_rays[0] * NATIVE_K[0, 0], native_rays[0] * NATIVE_K[0, 0], atol=0.2)
    np.testing.assert_allclose(stored_rays[1] * NATIVE_K[1, 1], native_rays[1] * NATIVE_K[1, 1], atol=0.2)


def test_intrinsics_follow_crop_and_resize_exactly() -> None:
    # 48 x 64 -> crop columns 8..55 -> 48 x 48 -> 32 x 32: scale 2/3 about pixel edges
    K = stored_intrinsics(NATIVE_K, (48, 64), 32)
    expected = [[40 * 2 / 3, 0, (31 - 8 + 0.5) * 2 / 3 - 0.5], [0, 42 * 2 / 3, (22.5 + 0.5) * 2 / 3 - 0.5], [0, 0, 1]]
    np.testing.assert_allclose(K, expected, atol=1e-12)
    np.testing.assert_allclose(stored_intrinsics(NATIVE_K, (64, 64), 64), NATIVE_K)


def test_depth_is_the_native_value_under_each_pixel_centre_in_depth_units(shards: tuple[Path, dict]) -> None:
    out_dir, summary = shards
    for files in all_samples(out_dir).values():
        meta = json.loads(files["meta.json"])
        position = (meta["frame"] - 10) // 2
        native = native_depth(48, 64, position)
        centres = ((np.arange(32) + 0.5) * 48 / 32).astype(int)
        expected = native[centres][:, centres + 8]  # rows, then columns of the centre crop
        expected[expected > 65.535] = 0  # beyond the encodable range: unknown
        stored = decode_png(files["depth.png"]) * meta["depth_unit"]
        np.testing.assert_allclose(stored, expected, atol=meta["depth_unit"] / 2 + 1e-6)
        assert (stored[:4] == 0).all()  # native rows 0..5 hold no reading or too far
    assert summary["depth_out_of_range_pixels"] > 0


def test_manifest_lists_exactly_the_tar_contents_in_even_sequence_contiguous_shards(shards: tuple[Path, dict]) -> None:
    out_dir, summary = shards
    table = pq.read_table(out_dir / MANIFEST)
    manifest = table.to_pandas()
    assert list(manifest.columns) == ["shard", "key", "dataset", "sequence", "group", "frame", "split", "sha256"]
    entries = json.loads(table.schema.metadata[SHARD_TABLE_KEY])
    counts = {name: entry["samples"] for name, entry in entries.items()}
    assert all(entry["sha256"] == shard_digests(str(out_dir / name))[0] for name, entry in entries.items())
    tars = sorted(p.name for p in out_dir.glob("*.tar"))
    assert sorted(counts) == tars and sorted(p.name for p in out_dir.iterdir()) == sorted(tars + [MANIFEST])
    for name in tars:
        rows = manifest[manifest.shard == name]
        assert list(rows.key) == list(read_tar(out_dir / name)) and len(rows) == counts[name]
        assert set(rows.split) == {name.split("-")[0]}
    assert manifest.key.is_unique
    for split, n_shards in summary["shards"].items():
        sizes = [counts[name] for name in tars if name.startswith(split)]
        assert n_shards % 2 == 0 and len(sizes) == n_shards and max(sizes) - min(sizes) <= 1
    # sequence-contiguous: walking the shards in order visits each sequence's frames once, in order
    for _, rows in manifest.groupby("sequence", sort=False):
        assert list(rows.frame) == sorted(rows.frame) and np.all(np.diff(rows.index) == 1)
    assert summary["samples"] == {"train": 8, "val": 4, "test": 4}
    assert summary["shards"] == {"train": 4, "val": 2, "test": 2}


def test_a_plain_webdataset_pipeline_reads_the_shards_back(shards: tuple[Path, dict]) -> None:
    out_dir, _ = shards
    urls = [str(p) for p in sorted(out_dir.glob("train-*.tar"))]
    samples = list(wds.WebDataset(urls, shardshuffle=False).decode("rgb8"))
    assert len(samples) == 8
    for sample in samples:
        meta = sample["meta.json"]
        assert isinstance(meta, dict) and meta["split"] == "train"
        position = (meta["frame"] - 10) // 2
        # colours in RGB order, as PIL reads them: blue holds the frame index
        assert sample["cur.png"].shape == (32, 32, 3) and np.all(sample["cur.png"][..., 2] == 40 * position)


def test_identical_bytes_with_one_and_two_worker_processes(tmp_path: Path, shards: tuple[Path, dict]) -> None:
    out_dir, _ = shards
    summary = write_dataset_shards(SyntheticSource(), "simcol", small_params(workers=2), tmp_path / "two")
    assert summary["shards"] == {"train": 4, "val": 2, "test": 2}
    assert_same_files(out_dir, tmp_path / "two")


def test_worker_processes_start_cleanly_while_the_caller_runs_other_threads(
    tmp_path: Path, shards: tuple[Path, dict]
) -> None:
    release = threading.Event()
    thread = threading.Thread(target=release.wait)
    thread.start()
    try:
        assert pool_context().get_start_method() != "fork"  # a forked child would inherit that thread's locks
        write_dataset_shards(SyntheticSource(), "simcol", small_params(workers=2), tmp_path / "two")
    finally:
        release.set()
        thread.join()
    assert_same_files(shards[0], tmp_path / "two")


def test_interrupted_run_leaves_output_untouched_and_a_rerun_finishes_the_rest(
    tmp_path: Path, shards: tuple[Path, dict]
) -> None:
    out_dir = tmp_path / "simcol"
    write_dataset_shards(SyntheticSource(), "simcol", small_params(size=16), out_dir)
    before = {p.name: p.read_bytes() for p in out_dir.iterdir()}
    marker = tmp_path / "broken"
    marker.touch()
    with pytest.raises(DataFormatError, match="unreadable image"):
        write_dataset_shards(SyntheticSource(broken=str(marker)), "simcol", small_params(), out_dir)
    assert {p.name: p.read_bytes() for p in out_dir.iterdir()} == before
    marker.unlink()
    summary = write_dataset_shards(SyntheticSource(broken=str(marker)), "simcol", small_params(), out_dir)
    # the train and val shards, written before the broken test frame, are kept
    assert summary["shards_reused"] == 6
    assert_same_files(shards[0], out_dir)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


@pytest.mark.parametrize(("failure", "error"), [("error", DataFormatError), ("crash", BrokenProcessPool)])
def test_a_failing_or_killed_worker_process_leaves_output_untouched(
    tmp_path: Path, shards: tuple[Path, dict], failure: str, error: type
) -> None:
    out_dir = tmp_path / "simcol"
    marker = tmp_path / "broken"
    marker.touch()
    source = SyntheticSource(broken=str(marker), failure=failure)
    with pytest.raises(error):
        write_dataset_shards(source, "simcol", small_params(workers=2), out_dir)
    assert not out_dir.exists()
    marker.unlink()
    write_dataset_shards(source, "simcol", small_params(workers=2), out_dir)
    assert_same_files(shards[0], out_dir)


def test_on_an_object_store_shards_are_written_in_place_and_the_manifest_last(
    tmp_path: Path, shards: tuple[Path, dict]
) -> None:
    # fsspec's in-memory filesystem stands for s3:// and the like: no rename, objects appear whole on upload
    fs, out = fsspec.filesystem("memory"), f"memory://{tmp_path.name}/simcol"
    write_dataset_shards(SyntheticSource(), "simcol", small_params(size=16), out)
    marker = tmp_path / "broken"
    marker.touch()
    try:
        with pytest.raises(DataFormatError, match="unreadable image"):
            write_dataset_shards(SyntheticSource(broken=str(marker)), "simcol", small_params(), out)
        left = sorted(path.rsplit("/", 1)[1] for path in fs.ls(f"/{tmp_path.name}/simcol", detail=False))
        # the old manifest went first: a reader finds none rather than one listing shards of the old run
        assert left == ["plan.json", *(f"train-00000{i}.tar" for i in range(4)), "val-000000.tar", "val-000001.tar"]
        marker.unlink()
        summary = write_dataset_shards(SyntheticSource(broken=str(marker)), "simcol", small_params(), out)
        assert summary["shards_reused"] == 6
        written = {path.rsplit("/", 1)[1]: fs.cat(path) for path in fs.ls(f"/{tmp_path.name}/simcol", detail=False)}
        assert written == {p.name: p.read_bytes() for p in shards[0].iterdir()}
    finally:
        fs.rm(f"/{tmp_path.name}", recursive=True)


def test_progress_lines_give_the_pace_and_the_time_left_at_most_every_interval() -> None:
    now, lines = [0.0], []
    progress = ShardProgress("simcol", total=4, kept=2, interval=10.0, clock=lambda: now[0], write=lines.append)
    shard = ShardResult(ShardEntry("train-000000.tar", 3, "0" * 64), frames_decoded=30, depth_out_of_range=0)
    for now[0] in (5.0, 12.0, 15.0, 40.0):
        progress.shard_done(shard)
    assert lines == [
        "[preprocess] simcol: 2/4 shards | 0.2 shards/s | ~0m12s left | 60 frames, 5.0 frames/s "
        "(2 shards kept from an interrupted run)",
        "[preprocess] simcol: 4/4 shards | 0.1 shards/s | done in 0m40s | 120 frames, 3.0 frames/s "
        "(2 shards kept from an interrupted run)",
    ]


def test_shards_that_ray_tasks_wrote_out_of_sight_are_an_error_naming_preprocess_out(tmp_path: Path) -> None:
    # a local output folder not shared with the other nodes: their shards landed on their own disks
    (tmp_path / "train-000000.tar").write_bytes(b"")
    results = [ShardResult(ShardEntry(name, 1, "0" * 64), 3, 0) for name in ("train-000000.tar", "val-000000.tar")]
    with pytest.raises(DataFormatError, match=r"\['val-000000.tar'\]... \(1 in all\) .* preprocess.out must be"):
        check_shards_arrived(str(tmp_path), results)
    check_shards_arrived(str(tmp_path), results[:1])


def test_depth_only_dataset_stores_every_frame_as_depth_and_meta(tmp_path: Path) -> None:
    out_dir = tmp_path / "scenenet"
    summary = write_dataset_shards(SyntheticSource(dataset="scenenet", frames=3), "scenenet", small_params(), out_dir)
    samples = all_samples(out_dir)
    assert len(samples) == 4 * 3 == sum(summary["samples"].values())
    for files in samples.values():
        assert set(files) == {"depth.png", "meta.json"}
        meta = json.loads(files["meta.json"])
        assert meta["T_world_cam"]["prev"] is None and meta["T_world_cam"]["next"] is None
        assert meta["depth_unit"] == DEPTH_UNIT_CM["scenenet"]
        position = (meta["frame"] - 10) // 2
        centre = native_depth(48, 64, position)[24, 32]  # stored pixel (16, 16) samples native (24, 32)
        assert decode_png(files["depth.png"])[16, 16] * meta["depth_unit"] == pytest.approx(centre, abs=0.05)


@pytest.mark.skipif(not SIMCOL_SAMPLE.is_dir(), reason=f"real SimCol3D sample not found at {SIMCOL_SAMPLE}")
def test_real_simcol_sample_gives_shards_whose_gt_explains_the_motion(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    from endoflow.geometry.pose import relative_pose
    from endoflow.geometry.warp import warp_frame

    params = small_params(size=64)
    params.data.simcol.root = str(SIMCOL_SAMPLE)
    summary = preprocess_dataset("simcol", params, tmp_path / "simcol")
    assert summary["samples"]["train"] == 8 and summary["shards"]["train"] % 2 == 0
    kitti = np.loadtxt(SIMCOL_SAMPLE / "S1_first10_converted_kitti3x4.txt").reshape(-1, 3, 4)
    errors = []
    for files in all_samples(tmp_path / "simcol").values():
        meta = json.loads(files["meta.json"])
        cam_txt = np.array([[227.60416, 0, 227.60416], [0, 237.5, 237.5], [0, 0, 1]])
        np.testing.assert_allclose(meta["K"], stored_intrinsics(cam_txt, (475, 475), 64), rtol=1e-9)
        np.testing.assert_allclose(np.array(meta["T_world_cam"]["cur"])[:3], kitti[meta["frame"]], atol=1e-6)
        image = {
            n: torch.from_numpy(decode_png(files[f"{n}.png"])).permute(2, 0, 1)[None].float() / 255
            for n in ("cur", "next")
        }
        depth = torch.from_numpy(decode_png(files["depth.png"]).astype(np.float32) * meta["depth_unit"])[None, None]
        poses = {n: torch.tensor(meta["T_world_cam"][n], dtype=torch.float32)[None] for n in ("cur", "next")}
        K = torch.tensor(meta["K"], dtype=torch.float32)[None]
        for T in (relative_pose(poses["next"], poses["cur"]), torch.eye(4)[None]):
            warped, valid = warp_frame(image["next"], depth, T, K)
            mask = valid & (depth > 0)
            errors.append(float(((warped - image["cur"]).abs().mean(1, keepdim=True))[mask].mean()))
    gt_errors, identity_errors = errors[0::2], errors[1::2]
    assert np.mean(gt_errors) < 0.8 * np.mean(identity_errors)


def assert_same_files(a: Path, b: Path) -> None:
    names = sorted(p.name for p in a.iterdir())
    assert names == sorted(p.name for p in b.iterdir())
    for name in names:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_train_offsets_give_each_train_target_its_offset_in_turn_and_leave_val_and_test_consecutive(tmp_path):
    from endoflow.data.loader import raw_samples
    from tests.fixtures_native import write_simcol
    from endoflow.data.shard_format import decode_meta

    root = tmp_path / "simcol"
    write_simcol(root, frames=12, size=32)
    params = Params()
    params.data.simcol.root = str(root)
    params.data.size = 32
    params.preprocess = params.preprocess.replace(out=str(tmp_path / "shards"), workers=1, train_offsets=[1, 3])
    preprocess_dataset("simcol", params, tmp_path / "shards" / "simcol")
    offsets: dict[str, dict[int, int]] = {}
    for tar in sorted((tmp_path / "shards" / "simcol").glob("*.tar")):
        for sample in raw_samples([str(tar)]):
            meta = decode_meta(sample["meta.json"], str(tar))
            ids = meta["frame_ids"]
            assert ids["next"] - ids["cur"] == ids["cur"] - ids["prev"] == meta["neighbour_offset"]
            offsets.setdefault(meta["split"], {})[meta["frame"]] = meta["neighbour_offset"]
    # frame i takes offset [1, 3][i % 2] where both its neighbours exist: even frames 2-10 at 1, odd 3-7 at 3
    assert offsets["train"] == {2: 1, 3: 3, 4: 1, 5: 3, 6: 1, 7: 3, 8: 1, 10: 1}
    assert offsets["val"] == offsets["test"] == {i: 1 for i in range(1, 11)}


@dataclass(frozen=True)
class BorderedSource(SyntheticSource):
    """The synthetic sequences seen through a circle in a black frame, as an endoscope's image is; each sequence's
    circle has its own radius (:meth:`radius`)."""

    def radius(self, name: str) -> float:
        return 22.0 if name == "S1" else 17.0 + int(name[1:]) % 4

    def sequence(self, name: str, split: str) -> Sequence:
        sequence = super().sequence(name, split)
        v, u = np.mgrid[:self.height, :self.width]
        radius = self.radius(name)
        inside = ((u - (self.width - 1) / 2) ** 2 + (v - (self.height - 1) / 2) ** 2 <= radius**2)[..., None]
        load = sequence.load_rgb
        sequence.load_rgb = lambda i: (load(i) * inside).astype(np.uint8)
        return sequence


def test_a_black_border_is_stored_as_the_field_of_view_and_its_ground_truth_is_unknown(tmp_path: Path) -> None:
    from endoflow.data.loader import raw_samples
    from endoflow.data.shard_format import decode_sample

    write_dataset_shards(BorderedSource(), "simcol", small_params(), tmp_path / "simcol")
    sample = decode_sample(next(raw_samples(sorted(str(p) for p in (tmp_path / "simcol").glob("train-*.tar")))))
    valid = sample["valid"][0]
    # a circle of radius 22 in the centre 48 x 48 of the frame, at 32 px: the corners out, the middle in
    assert not valid[0, 0] and not valid[-1, -1] and valid[16, 16] and 0.45 < valid.float().mean() < 0.75
    assert (sample["depth"][0][~valid] == 0).all() and (sample["depth"][0][valid] > 0).any()


def test_every_sample_carries_the_field_of_view_of_its_own_sequence(tmp_path: Path) -> None:
    """Shards of 3 samples hold the end of one sequence and the start of the next: each keeps its own circle."""
    from endoflow.data.field_of_view import field_of_view, resized_field_of_view
    from endoflow.data.loader import raw_samples
    from endoflow.data.shard_format import decode_sample

    source = BorderedSource()
    params = small_params()
    params.preprocess = params.preprocess.replace(shard_multiple=1)  # 3 + 3 + 2 train samples: one shard straddles
    write_dataset_shards(source, "simcol", params, tmp_path / "simcol")
    expected = {s.name: resized_field_of_view(field_of_view([s.load_rgb(i) for i in range(len(s))]), 32)
                for s in source()}
    assert len({m.tobytes() for m in expected.values()}) > 1
    shared = 0
    for shard in sorted((tmp_path / "simcol").glob("*.tar")):
        samples = [decode_sample(raw) for raw in raw_samples([str(shard)])]
        shared += len({s["meta"]["sequence"] for s in samples}) > 1
        for sample in samples:
            np.testing.assert_array_equal(sample["valid"][0].numpy(), expected[sample["meta"]["sequence"]])
    assert shared  # some shard holds two sequences
