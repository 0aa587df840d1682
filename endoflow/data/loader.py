"""Reading the shards of :mod:`endoflow.data.shard_format`: ordered evaluation, per-rank training batches.

Shard locations may be local paths or fsspec URLs (``file://``, ``s3://`` with s3fs installed, ...), so every
node of a cluster can read the same shards. Every shard is read through
:func:`~endoflow.data.shard_format.read_shard`, which checks it against its manifest entry (sample count and
SHA-256): damaged shards fail the read, naming the file, in training, validation and evaluation alike. Decoded
samples are laid out as :func:`~endoflow.data.shard_format.decode_sample` documents.

Distributed training (:func:`rank_batches`): every epoch the shards are dealt to the ranks by a permutation
drawn from ``(seed, epoch)``, so ranks read disjoint shards and each sees different shards over epochs.
Uneven shard counts or sizes would let one rank finish early and leave the others waiting forever in DDP's
all-reduce; instead every rank yields exactly :func:`batches_per_epoch` batches, the even share of the
epoch's samples, cycling through its own shards when they hold fewer samples than that.
"""

from __future__ import annotations

import itertools
import random
from functools import partial
from typing import Iterable, Iterator, Mapping, Optional

import numpy as np
import webdataset as wds

from endoflow.data.shard_format import (
    ShardEntry,
    collate_samples,
    decode_sample,
    read_shard,
    shard_entries,
    split_shards,
)


# --------------------------------------------------------------------------------------------- listing
def list_shards(root: str, split: str) -> list[str]:
    """The shards of ``split`` in the folder ``root`` (a local path or an fsspec URL), as its manifest lists them.

    Local paths come back as paths, URLs as URLs (``file:///abs/train-000000.tar``). A shard the manifest lists
    but the folder lacks is an error naming it (:func:`~endoflow.data.shard_format.split_shards`).
    """
    return split_shards(str(root), split)


# --------------------------------------------------------------------------------------------- reading
def raw_samples(urls: Iterable[str], entries: Optional[Mapping[str, ShardEntry]] = None) -> Iterator[dict]:
    """Undecoded samples of the shards, in order, each shard checked against its manifest entry.

    ``entries`` (URL -> entry) defaults to the manifests beside the shards.
    """
    urls = list(urls)
    entries = entries if entries is not None else shard_entries(urls)
    for url in urls:
        yield from read_shard(url, entries[url])


def triplet_dataset(
    urls: list[str], shuffle: bool = False, seed: int = 0, epoch: int = 0, shuffle_buffer: int = 256
) -> wds.DataPipeline:
    """Decoded samples of ``urls`` as an iterable dataset (usable with a torch ``DataLoader``).

    ``shuffle=False`` (evaluation) keeps shard and sample order, i.e. frames in sequence order. With
    ``shuffle=True`` shard order and a ``shuffle_buffer`` of samples are shuffled reproducibly from
    ``(seed, epoch)``: build one per epoch. ``DataLoader`` workers each read a disjoint subset of the shards.
    """
    order = _shard_permutation(len(urls), seed, epoch) if shuffle else range(len(urls))
    stages = [partial(iter, [urls[i] for i in order]), wds.split_by_worker,
              partial(raw_samples, entries=shard_entries(urls))]
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
    urls: list[str], world_size: int, batch_size: int, entries: Optional[Mapping[str, ShardEntry]] = None
) -> int:
    """Batches every rank yields per epoch: the even share of all samples, in full batches."""
    entries = entries if entries is not None else shard_entries(urls)
    return sum(entries[url].samples for url in urls) // world_size // batch_size


def rank_batches(
    urls: list[str],
    rank: int,
    world_size: int,
    batch_size: int,
    epoch: int,
    seed: int,
    shuffle_buffer: int = 256,
    entries: Optional[Mapping[str, ShardEntry]] = None,
) -> Iterator[dict]:
    """Collated training batches of ``rank`` for ``epoch``: exactly :func:`batches_per_epoch` of them.

    Call with the same ``urls``, ``seed`` and ``epoch`` on every rank. A rank dealt more than the even
    share leaves the rest of its samples for another epoch (the deal changes every epoch); one dealt less
    reads its own shards again. Samples are shuffled within the rank through a ``shuffle_buffer``.
    ``entries`` (URL -> manifest entry) defaults to the manifests beside the shards.
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be positive, got {batch_size}")
    entries = entries if entries is not None else shard_entries(urls)
    own = rank_shards(urls, rank, world_size, epoch, seed)
    count = batches_per_epoch(urls, world_size, batch_size, entries)
    if count and sum(entries[url].samples for url in own) == 0:
        raise ValueError(f"rank {rank} was dealt only empty shards this epoch; use fewer ranks or more data")
    rng = random.Random(f"{seed}-{epoch}-{rank}")
    samples = wds.shuffle(shuffle_buffer, shuffle_buffer, rng=rng)(_cycle(own, entries))
    batches = (collate_samples([decode_sample(s) for s in group]) for group in _groups(samples, batch_size))
    return itertools.islice(batches, count)


def _cycle(urls: list[str], entries: Mapping[str, ShardEntry]) -> Iterator[dict]:
    """Samples of ``urls`` over and over (a rank short of its share re-reads its own shards)."""
    while True:
        yield from raw_samples(urls, entries)


def _groups(items: Iterator[dict], size: int) -> Iterator[list[dict]]:
    while group := list(itertools.islice(items, size)):
        yield group
