"""Reading the shards of :mod:`endoflow.data.shards`: decoding, ordered evaluation, per-rank training batches.

Shard locations may be local paths or fsspec URLs (``file://``, ``s3://`` with s3fs installed, ...), so every
node of a cluster can read the same shards; tar streams are opened through fsspec and split into samples by
WebDataset's own tar iterators.

Decoded sample (:func:`decode_sample`), shapes per sample (a batch adds a leading ``B``):

- ``prev``, ``cur``, ``next``: ``[3, H, W]`` float32 RGB in [0, 1] (absent for depth-only datasets);
- ``depth``: ``[1, H, W]`` float32 z-depth of ``cur`` in cm, 0 where unknown;
- ``K``: ``[3, 3]`` float32 pixel intrinsics of the stored size;
- ``T_prev``, ``T_cur``, ``T_next``: ``[4, 4]`` float32 camera-to-world ``T_world_cam`` in cm, all NaN where
  unknown;
- ``meta``: the sample's ``meta.json`` as a dict; ``key``: its WebDataset key.

Distributed training (:func:`rank_batches`): every epoch the shards are dealt to the ranks by a permutation
drawn from ``(seed, epoch)``, so ranks read disjoint shards and each sees different shards over epochs.
Uneven shard counts or sizes would let one rank finish early and leave the others waiting forever in DDP's
all-reduce; instead every rank yields exactly :func:`batches_per_epoch` batches, the even share of the
epoch's samples, cycling through its own shards when they hold fewer samples than that.
"""

from __future__ import annotations

import itertools
from functools import partial
import json
import posixpath
import random
from typing import Iterable, Iterator, Mapping, Optional

import cv2
import fsspec
import numpy as np
import pyarrow.parquet as pq
import torch
import webdataset as wds
from webdataset.tariterators import group_by_keys, tar_file_expander

from endoflow.data.base import DataFormatError
from endoflow.data.shards import MANIFEST, SHARD_COUNTS_KEY, SPLITS

IMAGE_NAMES = ("prev", "cur", "next")
TENSOR_KEYS = ("prev", "cur", "next", "depth", "K", "T_prev", "T_cur", "T_next")


# --------------------------------------------------------------------------------------------- listing
def list_shards(root: str, split: str) -> list[str]:
    """Sorted shard URLs ``<root>/<split>-NNNNNN.tar``; ``root`` is a local path or an fsspec URL.

    Local paths come back as paths, URLs as URLs with the same protocol (``file:///abs/train-000000.tar``).
    """
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    root = str(root)
    fs, path = fsspec.core.url_to_fs(root)
    found = sorted(fs.glob(posixpath.join(path.rstrip("/"), f"{split}-*.tar")))
    if "://" in root:
        return [fs.unstrip_protocol(p) for p in found]
    return found


def shard_sample_counts(urls: Iterable[str]) -> dict[str, int]:
    """Samples per shard, from the ``manifest.parquet`` beside the shards (empty shards included)."""
    counts: dict[str, int] = {}
    by_folder: dict[str, list[str]] = {}
    for url in urls:
        by_folder.setdefault(posixpath.dirname(url), []).append(url)
    for folder, folder_urls in by_folder.items():
        manifest = posixpath.join(folder, MANIFEST)
        try:
            with fsspec.open(manifest, "rb") as f:
                metadata = pq.read_schema(f).metadata or {}
        except FileNotFoundError:
            raise DataFormatError(manifest, "manifest not found beside the shards") from None
        if SHARD_COUNTS_KEY not in metadata:
            raise DataFormatError(manifest, f"schema metadata {SHARD_COUNTS_KEY.decode()} with shard sizes missing")
        per_name = json.loads(metadata[SHARD_COUNTS_KEY])
        for url in folder_urls:
            name = posixpath.basename(url)
            if name not in per_name:
                raise DataFormatError(manifest, f"shard {name} is not listed")
            counts[url] = int(per_name[name])
    return counts


# -------------------------------------------------------------------------------------------- decoding
def decode_sample(sample: Mapping[str, object]) -> dict:
    """Raw WebDataset sample (extension -> bytes) to tensors; see the module docstring for the layout."""
    key = str(sample.get("__key__", "?"))
    if "meta.json" not in sample or "depth.png" not in sample:
        raise DataFormatError(key, f"sample needs meta.json and depth.png, has {sorted(sample)}")
    meta = json.loads(sample["meta.json"])
    out: dict = {"key": key, "meta": meta}
    for name in IMAGE_NAMES:
        if f"{name}.png" in sample:
            rgb = _decode_png(sample[f"{name}.png"], key, name)
            if rgb.ndim != 3 or rgb.dtype != np.uint8:
                raise DataFormatError(key, f"{name}.png: expected 8-bit RGB, found {rgb.dtype} {rgb.shape}")
            out[name] = torch.from_numpy(np.ascontiguousarray(rgb[..., ::-1].transpose(2, 0, 1))).float() / 255.0
    counts = _decode_png(sample["depth.png"], key, "depth")
    if counts.ndim != 2 or counts.dtype != np.uint16:
        raise DataFormatError(key, f"depth.png: expected 16-bit grey, found {counts.dtype} {counts.shape}")
    out["depth"] = torch.from_numpy(counts.astype(np.float32) * np.float32(meta["depth_unit"]))[None]
    out["K"] = torch.tensor(meta["K"], dtype=torch.float32)
    for name in IMAGE_NAMES:
        pose = meta["T_world_cam"][name]
        out[f"T_{name}"] = torch.full((4, 4), float("nan")) if pose is None else torch.tensor(pose, dtype=torch.float32)
    return out


def _decode_png(data: bytes, key: str, name: str) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DataFormatError(key, f"{name}.png cannot be decoded")
    return image


def collate_samples(samples: list[dict]) -> dict:
    """Stack decoded samples: tensors gain a batch dimension; ``meta`` and ``key`` become lists."""
    batch: dict = {name: torch.stack([s[name] for s in samples]) for name in TENSOR_KEYS if name in samples[0]}
    batch["meta"] = [s["meta"] for s in samples]
    batch["key"] = [s["key"] for s in samples]
    return batch


# --------------------------------------------------------------------------------------------- reading
def raw_samples(urls: Iterable[str]) -> Iterator[dict]:
    """Undecoded samples of the shards, in order (each opened through fsspec)."""
    return group_by_keys(tar_file_expander(_open_streams(urls)))


def _open_streams(urls: Iterable[str]) -> Iterator[dict]:
    for url in urls:
        with fsspec.open(url, "rb") as stream:
            yield {"url": url, "stream": stream}


def triplet_dataset(
    urls: list[str], shuffle: bool = False, seed: int = 0, epoch: int = 0, shuffle_buffer: int = 256
) -> wds.DataPipeline:
    """Decoded samples of ``urls`` as an iterable dataset (usable with a torch ``DataLoader``).

    ``shuffle=False`` (evaluation) keeps shard and sample order, i.e. frames in sequence order. With
    ``shuffle=True`` shard order and a ``shuffle_buffer`` of samples are shuffled reproducibly from
    ``(seed, epoch)``: build one per epoch. ``DataLoader`` workers each read a disjoint subset of the shards.
    """
    order = _shard_permutation(len(urls), seed, epoch) if shuffle else range(len(urls))
    stages = [partial(iter, [urls[i] for i in order]), wds.split_by_worker, raw_samples]
    if shuffle:
        stages.append(wds.shuffle(shuffle_buffer, rng=random.Random(f"{seed}-{epoch}")))
    stages.append(wds.map(decode_sample))
    return wds.DataPipeline(*stages)


def _shard_permutation(count: int, seed: int, epoch: int) -> list[int]:
    return [int(i) for i in np.random.default_rng([seed, epoch]).permutation(count)]


# ------------------------------------------------------------------------------------- distributed ranks
def rank_shards(urls: list[str], rank: int, world_size: int, epoch: int, seed: int) -> list[str]:
    """The shards of ``rank`` this epoch: disjoint across ranks, together all of ``urls``."""
    if world_size < 1 or not 0 <= rank < world_size:
        raise ValueError(f"rank {rank} is not in [0, world_size={world_size})")
    if len(urls) < world_size:
        raise ValueError(f"{len(urls)} shards cannot give each of {world_size} ranks its own shard")
    order = _shard_permutation(len(urls), seed, epoch)
    return [urls[i] for i in order[rank::world_size]]


def batches_per_epoch(
    urls: list[str], world_size: int, batch_size: int, shard_sizes: Optional[Mapping[str, int]] = None
) -> int:
    """Batches every rank yields per epoch: the even share of all samples, in full batches."""
    sizes = shard_sizes if shard_sizes is not None else shard_sample_counts(urls)
    return sum(sizes[url] for url in urls) // world_size // batch_size


def rank_batches(
    urls: list[str],
    rank: int,
    world_size: int,
    batch_size: int,
    epoch: int,
    seed: int,
    shuffle_buffer: int = 256,
    shard_sizes: Optional[Mapping[str, int]] = None,
) -> Iterator[dict]:
    """Collated training batches of ``rank`` for ``epoch``: exactly :func:`batches_per_epoch` of them.

    Call with the same ``urls``, ``seed`` and ``epoch`` on every rank. A rank dealt more than the even
    share leaves the rest of its samples for another epoch (the deal changes every epoch); one dealt less
    reads its own shards again. Samples are shuffled within the rank through a ``shuffle_buffer``.
    ``shard_sizes`` (URL -> samples) defaults to the manifest beside the shards.
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be positive, got {batch_size}")
    sizes = shard_sizes if shard_sizes is not None else shard_sample_counts(urls)
    own = rank_shards(urls, rank, world_size, epoch, seed)
    count = batches_per_epoch(urls, world_size, batch_size, sizes)
    if count and sum(sizes[url] for url in own) == 0:
        raise ValueError(f"rank {rank} was dealt only empty shards this epoch; use fewer ranks or more data")
    rng = random.Random(f"{seed}-{epoch}-{rank}")
    samples = wds.shuffle(shuffle_buffer, shuffle_buffer, rng=rng)(_cycle(own))
    batches = (collate_samples([decode_sample(s) for s in group]) for group in _groups(samples, batch_size))
    return itertools.islice(batches, count)


def _cycle(urls: list[str]) -> Iterator[dict]:
    """Samples of ``urls`` over and over (a rank short of its share re-reads its own shards)."""
    while True:
        yield from raw_samples(urls)


def _groups(items: Iterator[dict], size: int) -> Iterator[list[dict]]:
    while group := list(itertools.islice(items, size)):
        yield group
