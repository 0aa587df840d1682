"""Reading shards back: decoded tensors, shard listing by path and URL, ordered and per-rank iteration, in
the training process or in loader processes (``train.loader_workers``).

Training shards here are deliberately uneven: 5 shards of 2 or 3 samples dealt to 2 ranks.
"""

from __future__ import annotations

import collections
import itertools
import json
import shutil
from pathlib import Path

import fsspec
import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
import webdataset as wds

from endoflow.config import ConfigError, params_from_dict
from endoflow.data.loader import (
    PREFETCH_BATCHES,
    batch_shares,
    batches_per_epoch,
    epoch_loader,
    list_shards,
    mixed_rank_batches,
    rank_batches,
    rank_epoch,
    rank_shards,
    raw_samples,
    triplet_dataset,
    worker_batches,
)
from endoflow.data.shard_format import (
    MANIFEST,
    MANIFEST_SCHEMA,
    ShardEntry,
    collate_samples,
    decode_sample,
    manifest_bytes,
    shard_digests,
    shard_entries,
    shard_name,
)
from endoflow.data.shards import write_dataset_shards
from endoflow.devices import batch_to_device
from endoflow.errors import DataFormatError
from endoflow.training.ray_trainer import training_fingerprint
from tests.module_temp import ModuleTemp
from tests.test_config import defaults_with
from tests.test_shards import SyntheticSource, native_pose, small_params


@pytest.fixture(scope="module")
def shard_dir(module_tmp: ModuleTemp) -> Path:
    out_dir = module_tmp("loader") / "simcol"
    params = small_params()
    params.preprocess = params.preprocess.replace(samples_per_shard=3, shard_multiple=5)
    write_dataset_shards(SyntheticSource(frames=8), "simcol", params, out_dir)
    return out_dir


def manifest_keys(shard_dir: Path, split: str) -> list[str]:
    manifest = pq.read_table(shard_dir / MANIFEST).to_pandas()
    return list(manifest[manifest.split == split].key)


def test_shards_are_listed_sorted_by_path_and_by_file_url(shard_dir: Path) -> None:
    paths = list_shards(shard_dir, "train")
    assert paths == [str(shard_dir / f"train-{i:06d}.tar") for i in range(5)]
    urls = list_shards(f"file://{shard_dir}", "train")
    assert urls == [f"file://{p}" for p in paths]
    assert [s["__key__"] for s in raw_samples(urls)] == [s["__key__"] for s in raw_samples(paths)]
    assert [e.samples for e in shard_entries(urls).values()] == [2, 2, 3, 2, 3]
    with pytest.raises(ValueError, match="split"):
        list_shards(shard_dir, "training")


def test_shards_on_another_fsspec_filesystem_are_listed_counted_and_read(shard_dir: Path) -> None:
    memory = fsspec.filesystem("memory")
    for path in shard_dir.iterdir():
        memory.pipe(f"/loader-test/{path.name}", path.read_bytes())
    try:
        urls = list_shards("memory://loader-test", "train")
        assert urls == [f"memory:///loader-test/train-{i:06d}.tar" for i in range(5)]
        assert list({url: e.samples for url, e in shard_entries(urls).items()}.values()) == [2, 2, 3, 2, 3]
        batches = list(rank_batches(urls, 1, 2, batch_size=2, epoch=0, seed=0))
        assert len(batches) == 3
    finally:
        memory.rm("/loader-test", recursive=True)


def test_decoded_sample_has_float_tensors_in_the_documented_units(shard_dir: Path) -> None:
    sample = decode_sample(next(raw_samples(list_shards(shard_dir, "val"))))
    meta = sample["meta"]
    position = (meta["frame"] - 10) // 2
    for name, shift in (("prev", -1), ("cur", 0), ("next", 1)):
        image = sample[name]
        assert image.shape == (3, 32, 32) and image.dtype == torch.float32
        assert 0.0 <= image.min() and image.max() <= 1.0
        # channel 2 (blue) holds the frame index: channels are RGB, scaled by 1/255
        assert torch.allclose(image[2], torch.full((32, 32), 40 * (position + shift) / 255.0))
        np.testing.assert_allclose(sample[f"T_{name}"].numpy(), native_pose(position + shift), atol=1e-6)
    assert sample["depth"].shape == (1, 32, 32) and sample["depth"].dtype == torch.float32
    valid = sample["depth"][sample["depth"] > 0]
    assert 5.0 + 0.5 * position <= valid.min() and valid.max() < 5.0 + 0.5 * position + 2.0  # cm
    assert torch.equal(sample["K"], torch.tensor(meta["K"], dtype=torch.float32))
    assert sample["key"] == f"simcol-{meta['sequence']}-{meta['frame']:06d}"


def test_training_batches_hand_over_8_bit_images_that_scale_to_the_decoded_floats(shard_dir: Path) -> None:
    urls = list_shards(shard_dir, "val")
    decoded = {s["key"]: s for s in triplet_dataset(urls)}
    for loader_workers in (0, 2):
        for batch in rank_batches(urls, 0, 1, batch_size=2, epoch=0, seed=0, loader_workers=loader_workers):
            on_device = batch_to_device(batch, torch.device("cpu"), "float32")
            for name in ("prev", "cur", "next"):
                assert batch[name].dtype == torch.uint8
                expected = torch.stack([decoded[key][name] for key in batch["key"]])
                assert torch.equal(on_device[name], expected)
            assert batch["depth"].dtype == torch.float32


def test_unknown_poses_decode_as_nan_and_depth_only_samples_have_no_images(tmp_path: Path) -> None:
    write_dataset_shards(SyntheticSource(dataset="scenenet", frames=2), "scenenet", small_params(), tmp_path / "sn")
    sample = decode_sample(next(raw_samples(list_shards(tmp_path / "sn", "train"))))
    assert "cur" not in sample and sample["depth"].shape == (1, 32, 32)
    assert torch.isnan(sample["T_prev"]).all() and torch.isnan(sample["T_next"]).all()
    assert torch.isfinite(sample["T_cur"]).all()


def test_evaluation_order_is_the_manifest_order_and_shuffling_is_reproducible(shard_dir: Path) -> None:
    urls = list_shards(shard_dir, "train")
    ordered = manifest_keys(shard_dir, "train")
    assert [s["key"] for s in triplet_dataset(urls)] == ordered
    shuffled = [s["key"] for s in triplet_dataset(urls, shuffle=True, seed=3, shuffle_buffer=4)]
    assert sorted(shuffled) == sorted(ordered) and shuffled != ordered
    assert shuffled == [s["key"] for s in triplet_dataset(urls, shuffle=True, seed=3, shuffle_buffer=4)]
    loader = torch.utils.data.DataLoader(triplet_dataset(urls), batch_size=4, collate_fn=collate_samples)
    first = next(iter(loader))
    assert first["cur"].shape == (4, 3, 32, 32) and first["T_cur"].shape == (4, 4, 4) and len(first["meta"]) == 4


def test_ranks_read_disjoint_shards_and_yield_equal_batch_counts_from_uneven_shards(shard_dir: Path) -> None:
    urls = list_shards(f"file://{shard_dir}", "train")
    key_shard = {key: i for i, url in enumerate(urls) for key in (s["__key__"] for s in raw_samples([url]))}
    assignments = []
    for epoch in range(3):
        own = [rank_shards(urls, rank, 2, epoch, seed=7) for rank in (0, 1)]
        assert sorted(own[0] + own[1]) == urls and not set(own[0]) & set(own[1])
        assert {len(own[0]), len(own[1])} == {2, 3}
        assignments.append(own[0])
        expected = batches_per_epoch(urls, world_size=2, batch_size=2)
        assert expected == 12 // 2 // 2
        for rank in (0, 1):
            batches = list(rank_batches(urls, rank, 2, batch_size=2, epoch=epoch, seed=7, shuffle_buffer=3))
            assert len(batches) == expected
            assert all(b["cur"].shape == (2, 3, 32, 32) for b in batches)
            seen_shards = {urls[key_shard[key]] for b in batches for key in b["key"]}
            assert seen_shards <= set(own[rank])
    assert len({tuple(a) for a in assignments}) > 1, "the shard assignment should change between epochs"


def write_shard_folder(folder: Path, samples: list[dict], sizes: list[int], prefix: str = "uneven") -> list[str]:
    """Train shards of the given sizes, cycling through ``samples`` under new keys (``<prefix>-<shard>-<i>``), with
    a true manifest."""
    folder.mkdir()
    pool = itertools.cycle(samples)
    entries, rows = [], {name: [] for name in MANIFEST_SCHEMA.names}
    for index, size in enumerate(sizes):
        name = shard_name("train", index)
        with wds.TarWriter(str(folder / name), encoder=False, mtime=0) as tar:
            for i in range(size):
                sample = {k: v for k, v in next(pool).items() if not k.startswith("__")}
                key = f"{prefix}-{index}-{i}"
                tar.write({"__key__": key, **sample})
                meta = json.loads(sample["meta.json"])
                for column, value in (("shard", name), ("key", key), ("dataset", meta["dataset"]),
                                      ("sequence", meta["sequence"]), ("group", meta["group"]),
                                      ("frame", meta["frame"]), ("split", "train")):
                    rows[column].append(value)
        file_digest, digests = shard_digests(str(folder / name))
        rows["sha256"].extend(digest for _, digest in digests)
        entries.append(ShardEntry(name, size, file_digest))
    (folder / MANIFEST).write_bytes(manifest_bytes(rows, entries))
    return list_shards(folder, "train")


def test_a_rank_short_of_its_share_cycles_its_own_shards(shard_dir: Path, tmp_path: Path) -> None:
    samples = list(raw_samples(list_shards(shard_dir, "train")))
    urls = write_shard_folder(tmp_path / "uneven", samples, [1, 1, 1, 1, 20])  # the rank given 20 has plenty
    expected = batches_per_epoch(urls, 2, 3)
    for rank in (0, 1):
        own = rank_shards(urls, rank, 2, epoch=0, seed=0)
        batches = list(rank_batches(urls, rank, 2, batch_size=3, epoch=0, seed=0))
        assert len(batches) == expected == (4 + 20) // 2 // 3
        keys = [key for b in batches for key in b["key"]]
        own_keys = {s["__key__"] for s in raw_samples(own)}
        assert set(keys) <= own_keys


def test_more_ranks_than_shards_or_a_missing_manifest_fail_clearly(shard_dir: Path, tmp_path: Path) -> None:
    urls = list_shards(shard_dir, "train")
    with pytest.raises(ValueError, match="5 shards cannot give each of 6 ranks"):
        next(rank_batches(urls, 0, 6, batch_size=1, epoch=0, seed=0))
    copy = tmp_path / "train-000000.tar"
    copy.write_bytes(Path(urls[0]).read_bytes())
    with pytest.raises(DataFormatError, match="manifest not found"):
        shard_entries([str(copy)])
    with pytest.raises(DataFormatError, match="manifest not found"):
        next(raw_samples([str(copy)]))


# ----------------------------------------------------------------------------------------- loader processes
LOADER_WORKERS = [0, 1, 2, 4]  # 4: more loader processes than a rank has shards (2 or 3) or batches (3)
# torch warns when a DataLoader starts more processes than this machine has cores: intended here
MORE_PROCESSES_THAN_CORES = pytest.mark.filterwarnings("ignore:This DataLoader will create")


def keys_of(batches) -> list[str]:
    return [key for batch in batches for key in batch["key"]]


@MORE_PROCESSES_THAN_CORES
@pytest.mark.parametrize("loader_workers", LOADER_WORKERS)
def test_every_rank_gets_its_even_share_from_its_own_shards_with_any_number_of_loader_processes(
        shard_dir: Path, loader_workers: int) -> None:
    urls = list_shards(shard_dir, "train")
    expected = batches_per_epoch(urls, world_size=2, batch_size=2)
    seen = []
    for rank in (0, 1):
        batches = list(rank_batches(urls, rank, 2, batch_size=2, epoch=1, seed=7, loader_workers=loader_workers))
        assert len(batches) == expected == 3
        assert all(b["cur"].shape == (2, 3, 32, 32) and b["depth"].shape == (2, 1, 32, 32) for b in batches)
        keys = keys_of(batches)
        own = [s["__key__"] for s in raw_samples(rank_shards(urls, rank, 2, epoch=1, seed=7))]
        assert set(keys) <= set(own)
        # a rank short of its 6 samples re-reads its own: every sample as often as another, give or take one
        uses = collections.Counter(keys)
        assert max(uses.values()) - min(uses[key] for key in own) <= 1 and len(uses) == min(len(own), 6)
        seen.append(set(keys))
    assert not seen[0] & seen[1]


@MORE_PROCESSES_THAN_CORES
def test_a_rank_with_samples_to_spare_uses_each_once_whatever_the_loader_processes(
        shard_dir: Path, tmp_path: Path) -> None:
    samples = list(raw_samples(list_shards(shard_dir, "train")))
    urls = write_shard_folder(tmp_path / "uneven", samples, [1, 1, 1, 1, 20])
    rich = next(rank for rank in (0, 1) if urls[4] in rank_shards(urls, rank, 2, epoch=0, seed=0))  # 20 samples
    for loader_workers in (0, 2, 3):
        keys = keys_of(rank_batches(urls, rich, 2, batch_size=3, epoch=0, seed=0, loader_workers=loader_workers))
        assert len(keys) == len(set(keys)) == 4 * 3


@MORE_PROCESSES_THAN_CORES
def test_the_same_seed_gives_the_same_batches_and_one_loader_process_matches_none(shard_dir: Path) -> None:
    urls = list_shards(shard_dir, "train")

    def epoch(loader_workers: int, epoch: int = 0) -> list[list[str]]:
        return [b["key"] for b in rank_batches(urls, 0, 2, batch_size=2, epoch=epoch, seed=3, shuffle_buffer=4,
                                               loader_workers=loader_workers)]

    assert epoch(2) == epoch(2) and epoch(4) == epoch(4)
    assert epoch(0) == epoch(1)
    assert epoch(0, epoch=1) != epoch(0) and epoch(2, epoch=1) != epoch(2)


def test_loader_processes_take_contiguous_runs_of_batches_the_first_ones_longer() -> None:
    for batches, workers in itertools.product(range(8), range(1, 5)):
        runs = [worker_batches(batches, w, workers) for w in range(workers)]
        assert [i for run in runs for i in run] == list(range(batches))
        lengths = [len(run) for run in runs]
        assert lengths == sorted(lengths, reverse=True) and lengths[0] - lengths[-1] <= 1


def test_a_capped_epoch_yields_its_cap_and_reading_batches_leaves_the_training_random_state_alone(
        shard_dir: Path) -> None:
    urls = list_shards(shard_dir, "train")
    torch.manual_seed(0)
    state = torch.get_rng_state()
    capped = list(rank_batches(urls, 0, 2, batch_size=2, epoch=0, seed=0, loader_workers=2, max_batches=2))
    assert len(capped) == 2 and len(list(rank_batches(urls, 0, 1, batch_size=1, epoch=0, seed=0,
                                                      loader_workers=2, max_batches=100))) == 12
    assert torch.equal(torch.get_rng_state(), state)


@pytest.mark.parametrize("damage", ["bytes after the tar end", "a changed sample"])
def test_a_damaged_shard_read_in_a_loader_process_fails_naming_it(shard_dir: Path, tmp_path: Path,
                                                                 damage: str) -> None:
    folder = tmp_path / "copy"
    shutil.copytree(shard_dir, folder)
    urls = list_shards(folder, "train")
    shard = Path(urls[3])
    if damage == "bytes after the tar end":
        with open(shard, "ab") as f:
            f.write(b"\0" * 1024)
    else:
        data = bytearray(shard.read_bytes())
        at = data.index(b'"frame": ') + len(b'"frame": ')
        data[at:at + 1] = b"9" if data[at:at + 1] != b"9" else b"8"
        shard.write_bytes(bytes(data))
    with pytest.raises(DataFormatError, match="SHA-256") as caught:
        list(rank_batches(urls, 0, 1, batch_size=1, epoch=0, seed=0, loader_workers=2))  # every sample of one rank
    assert caught.value.path == shard


def test_batches_come_in_pinned_memory_when_asked(shard_dir: Path) -> None:
    epoch_data = rank_epoch(list_shards(shard_dir, "train"), 0, 2, batch_size=2, epoch=0, seed=0)
    loader = epoch_loader(epoch_data, loader_workers=2, pin_memory=True)
    assert loader.pin_memory and loader.num_workers == 2 and loader.prefetch_factor == PREFETCH_BATCHES
    assert not epoch_loader(epoch_data, loader_workers=0, pin_memory=False).pin_memory
    if torch.cuda.is_available():  # pinning needs a CUDA device
        assert all(batch["cur"].is_pinned() for batch in loader)


def test_loader_processes_must_fit_the_workers_cpus_and_shape_the_training_fingerprint(shard_dir: Path) -> None:
    with pytest.raises(ConfigError, match=r"train\.loader_workers \(2\) \+ 1 .* ray\.cpus_per_worker = 2"):
        params_from_dict(defaults_with({"train.loader_workers": 2, "ray.cpus_per_worker": 2.0}))
    with pytest.raises(ConfigError, match=r"train\.loader_workers must be >= 0"):
        params_from_dict(defaults_with({"train.loader_workers": -1}))
    fits = params_from_dict(defaults_with({"train.loader_workers": 2, "ray.cpus_per_worker": 3.0}))
    in_process = params_from_dict(defaults_with({"train.loader_workers": 0, "ray.cpus_per_worker": 3.0}))
    assert training_fingerprint(fits, str(shard_dir), None) != training_fingerprint(in_process, str(shard_dir), None)


# ------------------------------------------------------------------------------------------ several folders
def test_batch_shares_follow_the_weights_and_add_up_to_the_batch() -> None:
    assert batch_shares(12, [1.0]) == [12]
    assert batch_shares(12, [1.0, 1.0]) == [6, 6]
    assert batch_shares(12, [1.0, 0.5]) == [8, 4]
    assert batch_shares(4, [1.0, 1.0, 1.0]) == [2, 1, 1]  # the tie's extra sample to the first folder
    assert batch_shares(12, [1.0, 0.01]) == [12, 0]  # too small a weight to get a sample: the trainer refuses it
    for size, weights in itertools.product(range(1, 20), ([1.0, 0.3], [1.0, 2.0, 0.7], [1.0, 1e-3])):
        assert sum(batch_shares(size, weights)) == size
    with pytest.raises(ValueError, match="positive weights"):
        batch_shares(4, [1.0, 0.0])


@MORE_PROCESSES_THAN_CORES
def test_one_folder_mixed_with_nothing_gives_the_batches_of_one_folder(shard_dir: Path) -> None:
    urls = list_shards(shard_dir, "train")
    for loader_workers in (0, 2):
        alone = keys_of(rank_batches(urls, 1, 2, batch_size=2, epoch=3, seed=5, loader_workers=loader_workers))
        mixed = keys_of(mixed_rank_batches([(urls, 2)], 1, 2, epoch=3, seed=5, loader_workers=loader_workers))
        assert alone == mixed


@MORE_PROCESSES_THAN_CORES
def test_mixed_batches_take_each_folders_share_and_the_first_folder_sets_the_epoch(
        shard_dir: Path, tmp_path: Path) -> None:
    samples = list(raw_samples(list_shards(shard_dir, "train")))
    first = write_shard_folder(tmp_path / "first", samples, [4, 4], prefix="first")
    second = write_shard_folder(tmp_path / "second", samples, [1, 1], prefix="second")  # fewer than it is asked for
    for loader_workers in (0, 2):
        batches = list(mixed_rank_batches([(first, 3), (second, 1)], 0, 1, epoch=0, seed=0,
                                          loader_workers=loader_workers))
        assert len(batches) == batches_per_epoch(first, 1, 3) == 2
        # 3 of each batch from the first folder's 8 samples, 1 from the second's 2: each used once
        assert [[key.split("-")[0] for key in batch["key"]] for batch in batches] == [["first"] * 3 + ["second"]] * 2
        keys = keys_of(batches)
        assert len(set(keys)) == len(keys) == 8
