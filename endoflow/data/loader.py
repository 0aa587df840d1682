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

Several shard folders (``train.mix``): each batch takes a fixed number of samples from each folder
(:func:`batch_shares`), each folder's part read as above with that batch size (:func:`mixed_rank_batches`); an
epoch is one pass over the first folder, the others cycling through their own samples.

Loader processes (``train.loader_workers``): a rank's batches can be read, checked, decoded and collated by
worker processes of a torch ``DataLoader`` (:class:`RankEpoch`), so that the training thread only moves
finished batches to its device; their images stay 8-bit until there. The rank's epoch is a run of samples of its
own shards; each loader process takes a contiguous part of whole batches (:func:`worker_batches`) and reads only
the shards that part lies in.

Loader processes in order (:func:`ordered_loader`): evaluation needs its frames in sequence order; its dataset's
process ``w`` of ``W`` yields items ``w, w + W, ...`` (:func:`loader_turn`), and the ``DataLoader``, which takes
one item from each process in turn, gives them back in that order.
"""

from __future__ import annotations

import itertools
import random
from dataclasses import dataclass
from functools import partial
from typing import Iterable, Iterator, Mapping, Optional, Union

import numpy as np
import torch
import webdataset as wds
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from endoflow.data.shard_format import (
    ShardEntry,
    collate_samples,
    decode_sample,
    read_shard,
    shard_entries,
    split_shards,
)
from endoflow.errors import DataFormatError

# Batches each loader process keeps ready ahead of the training loop (DataLoader's prefetch_factor): with W
# processes up to 2 W collated batches wait in shared memory (/dev/shm; containers may need --shm-size).
PREFETCH_BATCHES = 2


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
    loader_workers: int = 0,
    pin_memory: bool = False,
    max_batches: Optional[int] = None,
) -> Iterator[dict]:
    """Collated training batches of ``rank`` for ``epoch``: exactly :func:`batches_per_epoch` of them, or
    ``max_batches`` if fewer (a capped epoch; the loader processes then read no further).

    Call with the same ``urls``, ``seed`` and ``epoch`` on every rank. A rank dealt more than the even
    share leaves the rest of its samples for another epoch (the deal changes every epoch); one dealt less
    reads its own shards again, every sample as often as another give or take one. ``entries`` (URL ->
    manifest entry) defaults to the manifests beside the shards.

    Images come as ``uint8`` (8-bit RGB as stored: a quarter of float32's bytes to hand over from a loader
    process and to copy to the device); :func:`endoflow.devices.batch_to_device` makes them float in [0, 1].
    ``loader_workers`` processes read, check, decode and collate (0: this process does). The order of the
    batches is fixed by ``(seed, epoch, rank, loader_workers)`` and depends on ``loader_workers`` (0 and 1
    give the same batches): each process shuffles its own part through a buffer of ``shuffle_buffer /
    loader_workers`` samples (the rank's memory for it stays that of one buffer) and the parts interleave
    batch by batch. A run resumes exactly only with the value it started with. ``pin_memory``: batches come
    in page-locked memory, for fast copies to a CUDA device. A damaged shard raises
    :class:`~endoflow.errors.DataFormatError` naming it, as it does when this process reads it.
    """
    epoch_data = rank_epoch(urls, rank, world_size, batch_size, epoch, seed, shuffle_buffer, entries, max_batches)
    return _raising_failures(epoch_loader(epoch_data, loader_workers, pin_memory))


def mixed_rank_batches(
    sources: list[tuple[list[str], int]],
    rank: int,
    world_size: int,
    epoch: int,
    seed: int,
    shuffle_buffer: int = 256,
    entries: Optional[Mapping[str, ShardEntry]] = None,
    loader_workers: int = 0,
    pin_memory: bool = False,
    max_batches: Optional[int] = None,
) -> Iterator[dict]:
    """:func:`rank_batches` over several shard folders: ``sources`` lists each folder's shards and how many samples
    of every batch it gives (:func:`batch_shares`). The epoch has the first folder's number of batches
    (:func:`batches_per_epoch` at its share); each folder's part of a batch is read as :func:`rank_batches` reads
    one folder, the others cycling through their samples as often as that takes. A single source is
    :func:`rank_batches` itself, batch for batch."""
    if not sources:
        raise ValueError("no shard folders to read")
    entries = entries if entries is not None else shard_entries([url for urls, _ in sources for url in urls])
    first_urls, first_share = sources[0]
    count = batches_per_epoch(first_urls, world_size, first_share, entries)
    if max_batches is not None:
        count = min(count, max_batches)
    parts = tuple(rank_epoch(urls, rank, world_size, share, epoch, seed, shuffle_buffer, entries, batches=count)
                  for urls, share in sources)
    data = parts[0] if len(parts) == 1 else MixedEpoch(parts)
    return _raising_failures(epoch_loader(data, loader_workers, pin_memory))


def batch_shares(batch_size: int, weights: list[float]) -> list[int]:
    """Samples of a ``batch_size`` batch each of the folders of ``weights`` gives: in proportion, the rounding by
    largest remainders (ties to the earlier folder), so they add up to ``batch_size``."""
    if batch_size < 1 or not weights or min(weights) <= 0:
        raise ValueError(f"need batch_size >= 1 and positive weights, got {batch_size} and {weights}")
    exact = [batch_size * w / sum(weights) for w in weights]
    shares = [int(e) for e in exact]
    by_remainder = sorted(range(len(weights)), key=lambda i: (shares[i] - exact[i], i))
    for i in by_remainder[: batch_size - sum(shares)]:
        shares[i] += 1
    return shares


def rank_epoch(
    urls: list[str],
    rank: int,
    world_size: int,
    batch_size: int,
    epoch: int,
    seed: int,
    shuffle_buffer: int = 256,
    entries: Optional[Mapping[str, ShardEntry]] = None,
    max_batches: Optional[int] = None,
    batches: Optional[int] = None,
) -> RankEpoch:
    """What ``rank`` reads in ``epoch`` (see :func:`rank_batches`), checked here rather than in a loader process;
    ``batches`` sets the count instead of :func:`batches_per_epoch` (a folder mixed into another's epoch)."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be positive, got {batch_size}")
    entries = entries if entries is not None else shard_entries(urls)
    own = rank_shards(urls, rank, world_size, epoch, seed)
    count = batches_per_epoch(urls, world_size, batch_size, entries) if batches is None else batches
    if max_batches is not None:
        count = min(count, max_batches)
    if count and sum(entries[url].samples for url in own) == 0:
        raise ValueError(f"rank {rank} was dealt only empty shards this epoch; use fewer ranks or more data")
    return RankEpoch(own, {url: entries[url] for url in own}, batch_size, count, seed, epoch, rank, shuffle_buffer)


def epoch_loader(epoch_data: RankEpoch | MixedEpoch, loader_workers: int, pin_memory: bool) -> DataLoader:
    """A ``DataLoader`` over ready batches (``batch_size=None``), with ``loader_workers`` processes.

    It gets its own random generator: starting it then draws nothing from this process's torch random state,
    which a resumed run restores and so must not depend on how data is loaded.
    """
    return DataLoader(epoch_data, batch_size=None, num_workers=loader_workers, pin_memory=pin_memory,
                      prefetch_factor=PREFETCH_BATCHES if loader_workers else None,
                      generator=torch.Generator().manual_seed(epoch_data.seed))


def ordered_loader(dataset: IterableDataset, loader_workers: int) -> Iterator:
    """The items of ``dataset``, read by ``loader_workers`` processes of a torch ``DataLoader`` (0: this process),
    handed over as the dataset yields them (tensors through shared memory, nothing collated).

    In the dataset's own order where its process ``w`` of ``W`` yields items ``w, w + W, ...`` (:func:`loader_turn`).
    An error of the data a loader process meets (:func:`failures_passed_on`) is raised here as it was raised there.
    Like :func:`epoch_loader`, it draws nothing from this process's torch random state.
    """
    loader = DataLoader(dataset, batch_size=None, num_workers=loader_workers,
                        prefetch_factor=PREFETCH_BATCHES if loader_workers else None,
                        generator=torch.Generator().manual_seed(0))
    return _raising_failures(loader)


def loader_turn() -> tuple[int, int]:
    """``(w, W)``: the calling code runs in loader process ``w`` of ``W``; ``(0, 1)`` outside loader processes."""
    info = get_worker_info()
    return (0, 1) if info is None else (info.id, info.num_workers)


def failures_passed_on(items: Iterable) -> Iterator:
    """``items``; in a loader process, a ``ValueError`` (a damaged shard's ``DataFormatError``, a sample refused)
    ends them as a :class:`ShardFailure` handed over like an item, which :func:`ordered_loader` raises."""
    try:
        yield from items
    except ValueError as error:
        if get_worker_info() is None:
            raise
        yield ShardFailure(error)


@dataclass(frozen=True)
class ShardFailure:
    """An error of the data (a damaged shard; a sample evaluation refuses) met in a loader process, passed on as a
    batch would be: torch re-raises a worker's error as a ``RuntimeError`` when its type takes more than a message,
    as ``DataFormatError`` does, and with the worker's traceback in the message otherwise."""

    error: ValueError


@dataclass(frozen=True)
class RankEpoch(IterableDataset):
    """One rank's collated batches of one epoch: ``batches`` of ``batch_size`` samples.

    The epoch's samples are the rank's ``shards`` read one after another, over and over if they hold too few:
    samples ``0 .. batches * batch_size - 1`` of that run. In a ``DataLoader`` with W processes, process ``w``
    collates the batches :func:`worker_batches` gives it, from just the samples they hold, shuffled through its
    own seeded buffer; the ``DataLoader`` takes one batch from each process in turn. ``entries`` holds the
    manifest entries of ``shards``.
    """

    shards: list[str]
    entries: dict[str, ShardEntry]
    batch_size: int
    batches: int
    seed: int
    epoch: int
    rank: int
    shuffle_buffer: int

    def __len__(self) -> int:
        return self.batches

    def __iter__(self) -> Iterator[Union[dict, ShardFailure]]:
        yield from _collated(self.sample_groups())

    def sample_groups(self) -> Iterator[list[dict]]:
        """The decoded samples of each batch of this loader process's part (:func:`worker_batches`)."""
        worker, workers = loader_turn()
        share = worker_batches(self.batches, worker, workers)
        samples = _sample_run(self.shards, self.entries, share.start * self.batch_size, share.stop * self.batch_size)
        buffer = max(1, self.shuffle_buffer // workers)
        rng = random.Random(f"{self.seed}-{self.epoch}-{self.rank}-{worker}")
        shuffled = wds.shuffle(buffer, buffer, rng=rng)(samples)
        for group in _groups(shuffled, self.batch_size):
            yield [decode_sample(sample, rgb8=True) for sample in group]


@dataclass(frozen=True)
class MixedEpoch(IterableDataset):
    """One rank's batches of one epoch drawn from several folders: batch ``i`` is batch ``i`` of every part
    (a :class:`RankEpoch` each, with that folder's share as its batch size and one count of batches), joined."""

    parts: tuple[RankEpoch, ...]

    def __len__(self) -> int:
        return self.parts[0].batches

    @property
    def seed(self) -> int:
        return self.parts[0].seed

    def __iter__(self) -> Iterator[Union[dict, ShardFailure]]:
        joined = ([sample for group in groups for sample in group]
                  for groups in zip(*(part.sample_groups() for part in self.parts)))
        yield from _collated(joined)


def _collated(groups: Iterator[list[dict]]) -> Iterator[Union[dict, ShardFailure]]:
    """Each group collated into a batch; a damaged shard met in a loader process is passed on as a
    :class:`ShardFailure` (raised here when this process reads)."""
    try:
        for group in groups:
            yield collate_samples(group)
    except DataFormatError as error:
        if get_worker_info() is None:
            raise
        yield ShardFailure(error)


def worker_batches(batches: int, worker: int, workers: int) -> range:
    """The batches (positions in the rank's epoch) that loader process ``worker`` of ``workers`` collates.

    A contiguous run per process, so each reads only the shards its run lies in; runs differ in length by at
    most one, the first processes taking the longer ones, so the ``DataLoader``'s turn-taking yields every
    batch and meets an exhausted process only in the last round.
    """
    base, extra = divmod(batches, workers)
    start = worker * base + min(worker, extra)
    return range(start, start + base + (worker < extra))


def _sample_run(urls: list[str], entries: Mapping[str, ShardEntry], start: int, stop: int) -> Iterator[dict]:
    """Samples ``start .. stop - 1`` of ``urls`` read one after another, over and over; only the shards
    holding them are read."""
    if start >= stop:
        return
    total = sum(entries[url].samples for url in urls)
    offset = start - start % total  # where the pass holding sample `start` begins
    while offset < stop:
        for url in urls:
            size = entries[url].samples
            begin, end = max(start - offset, 0), min(stop - offset, size)
            if begin < end:
                yield from _shard_part(url, entries[url], begin, end)
            offset += size


def _shard_part(url: str, entry: ShardEntry, begin: int, end: int) -> Iterator[dict]:
    """Samples ``begin .. end - 1`` of a shard. Read to its end, the shard's count and SHA-256 are checked as
    well; stopping earlier, every sample read has been checked."""
    samples = read_shard(url, entry)
    if end < entry.samples:
        samples = itertools.islice(samples, end)
    yield from itertools.islice(samples, begin, None)


def _raising_failures(batches: Iterable[Union[dict, ShardFailure]]) -> Iterator[dict]:
    for batch in batches:
        if isinstance(batch, ShardFailure):
            raise batch.error
        yield batch


def _groups(items: Iterator[dict], size: int) -> Iterator[list[dict]]:
    while group := list(itertools.islice(items, size)):
        yield group
