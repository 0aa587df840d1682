"""The shard format: the one definition that the writer and every reader of shards import.

A dataset's shard folder (written by :mod:`endoflow.data.shards`)::

    <folder>/train-000000.tar ... val-000000.tar ... test-000000.tar     manifest.parquet

Each tar holds samples as WebDataset members ``<key>.<member>``, members of a sample adjacent and in sorted
order. A complete sample is exactly :data:`TRIPLET_MEMBERS` (a target frame with its neighbours) or exactly
:data:`DEPTH_ONLY_MEMBERS` (depth-only datasets such as SceneNet):

- ``prev.png``, ``cur.png``, ``next.png``: RGB ``uint8`` at the stored square size.
- ``depth.png``: ``uint16`` z-depth of ``cur``, ``depth_cm = count * meta["depth_unit"]``, 0 = unknown.
- ``valid.png`` (triplets): ``uint8`` 255 where the sequence's frames see the scene, 0 outside its field of view
  (the black border of an endoscope's image: :mod:`endoflow.data.field_of_view`), one mask for the sequence.
- ``meta.json``: ``dataset``, ``sequence``, ``group``, ``split``, ``frame``, ``frame_ids``
  (``prev``/``cur``/``next``), ``neighbour_offset`` (how many regular frame steps ``prev`` and ``next`` lie from
  ``cur``; null when depth-only), ``K`` (3x3 at the stored size, pixel centres at integers), ``T_world_cam``
  (``prev``/``cur``/``next``: 4x4 camera-to-world in cm, or null), ``depth_unit`` (cm per count),
  ``native_size`` ``[H, W]``, ``intrinsics_known`` (false: ``K`` is assumed, the camera was never calibrated),
  ``ground_truth`` (``{"depth": bool, "pose": bool}``: whether the dataset has them at all; unlabelled video has
  neither, its ``depth.png`` is all 0 and its poses null, and consumers that score against ground truth refuse it).

``manifest.parquet`` has one row per sample (:data:`MANIFEST_SCHEMA`, in shard order, with the SHA-256 of the
sample's members, :func:`sample_sha256`) and, in its schema metadata under :data:`SHARD_TABLE_KEY`, every shard
(empty ones too) with its sample count and the SHA-256 of its bytes, all recorded when it was written. The
manifest is the list of shards (:func:`split_shards`): one that is listed but missing is an error. Every read
of a shard (:func:`read_shard`) is checked against the manifest: each sample as it is read (its key, its
members, their SHA-256), so a reader that stops part-way through a shard has still checked all it used; and at
the shard's end its sample count and the SHA-256 of its bytes. A mismatch is a
:class:`~endoflow.errors.DataFormatError` naming the shard file and what was expected.

A shard is read only if it is a regular file holding an uncompressed tar of plain-file members, each no larger
than the file: a device, a FIFO (or a link to one), a compressed or sparse archive is refused before anything is
read into memory, so a hostile shard can neither hang a reader nor make it allocate more than the file's size.

Locations may be local paths or fsspec URLs (``s3://...``, ``file:///...``).
"""

from __future__ import annotations

import hashlib
import json
import posixpath
import stat
import tarfile
from contextlib import contextmanager
from dataclasses import dataclass
from typing import IO, Collection, Iterable, Iterator, Mapping

import cv2
import fsspec
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from webdataset.tariterators import group_by_keys

from endoflow.config import DATASETS
from endoflow.devices import unit_float_images
from endoflow.errors import DataFormatError

SPLITS = ("train", "val", "test")
MANIFEST = "manifest.parquet"
# Parquet schema metadata key: JSON {shard name: {"samples": n, "sha256": hex}}, empty shards included.
SHARD_TABLE_KEY = b"endoflow.shards"
# Bumped whenever the bytes written for the same input change.
FORMAT_VERSION = 5

IMAGE_NAMES = ("prev", "cur", "next")
DEPTH_MEMBER = "depth.png"
META_MEMBER = "meta.json"
VALID_MEMBER = "valid.png"
TRIPLET_MEMBERS = frozenset({*(f"{name}.png" for name in IMAGE_NAMES), DEPTH_MEMBER, META_MEMBER, VALID_MEMBER})
DEPTH_ONLY_MEMBERS = frozenset({DEPTH_MEMBER, META_MEMBER})
META_KEYS = ("dataset", "depth_unit", "K", "T_world_cam", "sequence", "frame", "intrinsics_known", "ground_truth")
TENSOR_KEYS = ("prev", "cur", "next", "depth", "valid", "K", "intrinsics_known", "camera", "T_prev", "T_cur", "T_next")

MANIFEST_SCHEMA = pa.schema(
    [
        ("shard", pa.string()),
        ("key", pa.string()),
        ("dataset", pa.string()),
        ("sequence", pa.string()),
        ("group", pa.string()),
        ("frame", pa.int64()),
        ("split", pa.string()),
        ("sha256", pa.string()),
    ]
)
_HASH_BLOCK = 1 << 20
# The first bytes of compressed streams that tarfile would otherwise unpack (shards are plain tar).
_COMPRESSION_MAGIC = {b"\x1f\x8b": "gzip", b"BZh": "bzip2", b"\xfd7zXZ\x00": "xz", b"\x28\xb5\x2f\xfd": "zstd"}
# The only member types a shard holds: plain files (ustar and pre-POSIX regular files).
_PLAIN_MEMBER_TYPES = (tarfile.REGTYPE, tarfile.AREGTYPE)


@dataclass(frozen=True)
class ShardEntry:
    """A shard as the manifest records it: its samples' keys and SHA-256 in stored order, its bytes' SHA-256."""

    name: str
    samples: int
    sha256: str
    sample_sha256: tuple[tuple[str, str], ...] = ()


@dataclass(frozen=True)
class Manifest:
    """A shard folder's ``manifest.parquet``: the sample rows and every shard's entry."""

    location: str
    table: pa.Table
    shards: dict[str, ShardEntry]

    def entry(self, shard_url: str) -> ShardEntry:
        """The entry of a shard of this folder, by URL or path; an unlisted shard is an error."""
        name = posixpath.basename(shard_url)
        if name not in self.shards:
            raise DataFormatError(self.location, f"shard {name} is not listed")
        return self.shards[name]


# ------------------------------------------------------------------------------------------ names
def shard_name(split: str, index: int) -> str:
    """``<split>-NNNNNN.tar``."""
    return f"{split}-{index:06d}.tar"


def check_split(split: str) -> None:
    """``split`` must be one of :data:`SPLITS`."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")


def manifest_location(folder: str) -> str:
    """``<folder>/manifest.parquet`` for a path or an fsspec URL."""
    return posixpath.join(str(folder).rstrip("/"), MANIFEST)


# --------------------------------------------------------------------------------------- manifest
def manifest_bytes(rows: Mapping[str, list], shards: Iterable[ShardEntry]) -> bytes:
    """The bytes of ``manifest.parquet`` for sample ``rows`` (column -> values) and the ``shards``' entries."""
    table = pa.table({field.name: pa.array(rows[field.name], field.type) for field in MANIFEST_SCHEMA})
    entries = {entry.name: {"samples": entry.samples, "sha256": entry.sha256} for entry in shards}
    table = table.replace_schema_metadata({SHARD_TABLE_KEY: json.dumps(entries, sort_keys=True).encode()})
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    return sink.getvalue().to_pybytes()


def read_manifest(folder: str) -> Manifest:
    """The manifest of a shard folder (a path or an fsspec URL), checked against :data:`MANIFEST_SCHEMA`."""
    location = manifest_location(folder)
    try:
        with fsspec.open(location, "rb") as f:
            table = pq.read_table(f)
    except FileNotFoundError:
        raise DataFormatError(location, "manifest not found beside the shards (run the preprocess stage)") from None
    except (pa.ArrowInvalid, OSError) as exc:
        raise DataFormatError(location, f"not a readable Parquet file: {exc}") from None
    missing = [name for name in MANIFEST_SCHEMA.names if name not in table.column_names]
    if missing:
        raise DataFormatError(location, f"columns {missing} missing; expected {MANIFEST_SCHEMA.names}")
    metadata = table.schema.metadata or {}
    if SHARD_TABLE_KEY not in metadata:
        raise DataFormatError(
            location,
            f"schema metadata {SHARD_TABLE_KEY.decode()} (shard sizes and checksums) missing: written by an older "
            f"endoflow (format {FORMAT_VERSION} expected); rerun the preprocess stage",
        )
    table = table.select(MANIFEST_SCHEMA.names)
    return Manifest(location, table, _shard_table(location, metadata[SHARD_TABLE_KEY], table))


def _shard_table(location: str, raw: bytes, table: pa.Table) -> dict[str, ShardEntry]:
    """The shard entries of the schema metadata, each with its samples' rows."""
    per_shard: dict[str, list[tuple[str, str]]] = {}
    for shard, key, digest in zip(*(table.column(c).to_pylist() for c in ("shard", "key", "sha256"))):
        per_shard.setdefault(shard, []).append((key, digest))
    try:
        entries = {name: ShardEntry(name, int(e["samples"]), str(e["sha256"]), tuple(per_shard.get(name, ())))
                   for name, e in json.loads(raw).items()}
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise DataFormatError(location, f"shard table {SHARD_TABLE_KEY.decode()} is malformed ({exc!r}); "
                                        f"rerun the preprocess stage") from None
    unlisted = sorted(set(per_shard) - set(entries))
    wrong = [name for name, e in entries.items() if len(e.sample_sha256) != e.samples]
    if unlisted or wrong:
        raise DataFormatError(location, f"rows and shard table disagree (rows of unlisted shards {unlisted}, "
                                        f"sample counts differing for {wrong}); rerun the preprocess stage")
    return entries


def split_shards(folder: str, split: str) -> list[str]:
    """The shards of ``split`` that the manifest of ``folder`` lists, in order, as paths or URLs like ``folder``.

    Raises:
        DataFormatError: a listed shard is missing (naming it).
    """
    check_split(split)
    manifest = read_manifest(folder)
    names = sorted(name for name in manifest.shards if name.startswith(f"{split}-"))
    fs, path = fsspec.core.url_to_fs(str(folder))
    urls = []
    for name in names:
        shard = posixpath.join(path.rstrip("/"), name)
        url = fs.unstrip_protocol(shard) if "://" in str(folder) else shard
        if not fs.exists(shard):
            raise DataFormatError(url, f"shard listed in {MANIFEST} is missing "
                                       f"({manifest.entry(name).samples} samples)")
        urls.append(url)
    return urls


def shard_entries(urls: Iterable[str]) -> dict[str, ShardEntry]:
    """URL -> manifest entry for shards in any number of folders (each folder's manifest read once)."""
    by_folder: dict[str, list[str]] = {}
    for url in urls:
        by_folder.setdefault(posixpath.dirname(url), []).append(url)
    entries: dict[str, ShardEntry] = {}
    for folder, folder_urls in by_folder.items():
        manifest = read_manifest(folder)
        entries.update({url: manifest.entry(url) for url in folder_urls})
    return entries


def sample_sha256(sample: Mapping[str, object]) -> str:
    """SHA-256 over a sample's members (name, length, bytes) in sorted order; ``__``-keys are not members."""
    digest = hashlib.sha256()
    for name in sorted(k for k in sample if not k.startswith("__")):
        data = sample[name]
        digest.update(f"{name}:{len(data)}:".encode())
        digest.update(data)
    return digest.hexdigest()


class HashingWriter:
    """A write-only stream that hashes every byte written through it: the writer's side of a shard's SHA-256,
    taken while the shard is written rather than by reading it back."""

    def __init__(self, stream: IO[bytes]) -> None:
        self.stream = stream
        self.digest = hashlib.sha256()

    def write(self, data: bytes) -> int:
        self.digest.update(data)
        return self.stream.write(data)

    def flush(self) -> None:
        self.stream.flush()


def shard_digests(location: str) -> tuple[str, list[tuple[str, str]]]:
    """What the manifest records of a shard already on disk (one kept from an interrupted run): the SHA-256 of
    its bytes, and each sample's key and :func:`sample_sha256` in stored order."""
    with open_shard(location) as (reader, size):
        samples = [(str(sample["__key__"]), sample_sha256(sample))
                   for sample in group_by_keys(plain_tar_members(reader, location, size))]
        return reader.drain(), samples


# --------------------------------------------------------------------------------------- reading
class _HashingReader:
    """A read-only stream that hashes every byte read through it."""

    def __init__(self, stream: IO[bytes]) -> None:
        self.stream = stream
        self.digest = hashlib.sha256()

    def read(self, size: int = -1) -> bytes:
        data = self.stream.read(size)
        self.digest.update(data)
        return data

    def drain(self) -> str:
        """Read what the tar parser left (end-of-archive padding, or bytes after damage); the hex digest."""
        while self.read(_HASH_BLOCK):
            pass
        return self.digest.hexdigest()


@contextmanager
def open_shard(url: str) -> Iterator[tuple[_HashingReader, int]]:
    """A shard file opened for reading through a :class:`_HashingReader`, and its size in bytes.

    Raises:
        DataFormatError: naming ``url``: it is missing, is not a regular file (a device, a FIFO, a folder, or a
            link to one: reading ``/dev/zero`` never ends, opening a FIFO waits for a writer forever), or starts
            like a compressed stream.
    """
    size = regular_file_size(url)
    with fsspec.open(url, "rb") as stream:
        head = stream.read(max(len(magic) for magic in _COMPRESSION_MAGIC))
        stream.seek(0)
        for magic, compression in _COMPRESSION_MAGIC.items():
            if head.startswith(magic):
                raise DataFormatError(url, f"a {compression}-compressed file; expected an uncompressed tar "
                                           f"(as the preprocess stage writes)")
        yield _HashingReader(stream), size


def regular_file_size(url: str) -> int:
    """The size in bytes of the regular file at ``url`` (a path or an fsspec URL), links followed.

    Raises:
        DataFormatError: naming ``url``: it is missing or is not a regular file.
    """
    fs, path = fsspec.core.url_to_fs(url)
    try:
        info = fs.info(path)
    except FileNotFoundError:
        raise DataFormatError(url, "shard file not found; expected a tar file (rerun the preprocess stage)") from None
    if info.get("type") != "file":
        raise DataFormatError(url, f"is {_file_kind(info)}, not a regular file; expected a tar shard")
    return int(info["size"])


def _file_kind(info: Mapping) -> str:
    """What a non-regular file is, in words, from fsspec's ``info`` (a local file's ``mode`` tells the most)."""
    mode = info.get("mode")
    kinds = ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a FIFO"),
             (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a folder"))
    kind = next((name for test, name in kinds if mode is not None and test(mode)),
                f"an entry of type {info.get('type')!r}")
    return f"{kind} (through a link)" if info.get("islink") else kind


def plain_tar_members(stream: IO[bytes], url: str, size_bound: int) -> Iterator[dict]:
    """The members of the uncompressed tar ``stream`` as ``{"fname", "data", "__url__"}``, in stored order.

    Every member must be a plain file no larger than ``size_bound`` (the shard file's size: a member stored in
    the file cannot be larger), checked before its data is read: a sparse member declaring gigabytes is refused
    without reading them.

    Raises:
        DataFormatError: naming ``url`` and the member.
        tarfile.TarError: the bytes are not an uncompressed tar.
    """
    with tarfile.open(fileobj=stream, mode="r|") as tar:
        for member in tar:
            check_plain_member(member, url, size_bound)
            yield {"fname": member.name, "data": tar.extractfile(member).read(), "__url__": url}
            tar.members = []  # a stream keeps no list of the members passed


def check_plain_member(member: tarfile.TarInfo, url: str, size_bound: int) -> None:
    """A shard member must be a plain file of at most ``size_bound`` bytes."""
    if member.sparse is not None or member.type == tarfile.GNUTYPE_SPARSE:
        raise DataFormatError(url, f"member {member.name} is a sparse file declaring {member.size} bytes; "
                                   f"expected plain files only")
    if member.type not in _PLAIN_MEMBER_TYPES:
        raise DataFormatError(url, f"member {member.name} is not a plain file (tar type {member.type!r}); "
                                   f"expected plain files only")
    if member.size > size_bound:
        raise DataFormatError(url, f"member {member.name} declares {member.size} bytes, more than the shard's "
                                   f"{size_bound}; expected members stored in the file (damaged shard)")


def read_shard(url: str, entry: ShardEntry) -> Iterator[dict]:
    """The raw samples of one shard (member -> bytes, plus ``__key__`` and ``__url__``), in stored order.

    Raises:
        DataFormatError: naming ``url``: a shard that is not a regular file holding an uncompressed tar of
            plain-file members (:func:`open_shard`, :func:`plain_tar_members`); a sample whose key, members or
            SHA-256 differ from the manifest's (as soon as it is read, before it is yielded), or, after the last
            sample, a sample count or a SHA-256 of the whole file that differs from the manifest's ``entry``.
    """
    count = 0
    with open_shard(url) as (reader, size):
        try:
            for sample in group_by_keys(plain_tar_members(reader, url, size)):
                check_complete(sample, url)
                check_recorded(sample, entry, count, url)
                count += 1
                yield sample
        except (OSError, ValueError, EOFError, tarfile.TarError) as exc:
            if isinstance(exc, DataFormatError):
                raise
            raise DataFormatError(url, f"not a readable tar shard ({exc}); expected {entry.samples} samples") from None
        digest = reader.drain()
    if count != entry.samples:
        raise DataFormatError(url, f"{count} samples read, the manifest records {entry.samples} (damaged shard)")
    if digest != entry.sha256:
        raise DataFormatError(url, f"SHA-256 {digest[:16]}... differs from the manifest's {entry.sha256[:16]}... "
                                   f"(damaged or replaced shard)")


def read_shards(urls: Iterable[str], entries: Mapping[str, ShardEntry]) -> Iterator[dict]:
    """:func:`read_shard` of each URL in turn."""
    for url in urls:
        yield from read_shard(url, entries[url])


def check_recorded(sample: Mapping[str, object], entry: ShardEntry, index: int, url: str) -> None:
    """The ``index``-th sample of a shard must be the one the manifest recorded there, byte for byte."""
    key = sample.get("__key__", "?")
    if index >= len(entry.sample_sha256):
        raise DataFormatError(url, f"sample {key} is beyond the {entry.samples} samples the manifest records")
    expected_key, expected_digest = entry.sample_sha256[index]
    if key != expected_key:
        raise DataFormatError(url, f"sample {index} is {key}, the manifest records {expected_key} (damaged shard)")
    if sample_sha256(sample) != expected_digest:
        raise DataFormatError(url, f"sample {key}: SHA-256 of its members differs from the manifest's "
                                   f"(damaged or replaced shard)")


def check_complete(sample: Mapping[str, object], url: str) -> None:
    """A sample must hold exactly the members of a triplet or of a depth-only sample."""
    members = frozenset(name for name in sample if not name.startswith("__"))
    if members not in (TRIPLET_MEMBERS, DEPTH_ONLY_MEMBERS):
        raise DataFormatError(
            url,
            f"sample {sample.get('__key__', '?')} has members {sorted(members)}; expected "
            f"{sorted(TRIPLET_MEMBERS)} or {sorted(DEPTH_ONLY_MEMBERS)}",
        )


# -------------------------------------------------------------------------------------- decoding
def decode_sample(sample: Mapping[str, object], rgb8: bool = False, images: Collection[str] = IMAGE_NAMES) -> dict:
    """A raw sample to tensors (shapes per sample; a batch adds a leading ``B``):

    - ``prev``, ``cur``, ``next``: ``[3, H, W]`` float32 RGB in [0, 1] (absent for depth-only samples); with
      ``rgb8``, ``uint8`` RGB 0..255 as stored, for :func:`endoflow.devices.images_to_device` to scale on the
      device (:func:`endoflow.devices.unit_float_images`); only those named in ``images`` (the others are left
      encoded: a reader that needs one frame of the triplet decodes one PNG, not three);
    - ``depth``: ``[1, H, W]`` float32 z-depth of ``cur`` in cm, 0 where unknown or outside the field of view;
    - ``valid``: ``[1, H, W]`` bool, the field of view (triplets only);
    - ``K``: ``[3, 3]`` float32 pixel intrinsics of the stored size; ``intrinsics_known``: ``[]`` bool, False where
      K is assumed (a camera nobody calibrated: training learns it); ``camera``: ``[]`` int64, the dataset's
      position in :data:`~endoflow.config.DATASETS` (the camera learned intrinsics belong to);
    - ``T_prev``, ``T_cur``, ``T_next``: ``[4, 4]`` float32 camera-to-world ``T_world_cam`` in cm, all NaN
      where unknown;
    - ``meta``: the sample's ``meta.json`` as a dict; ``key``: its key.

    Errors name the shard file (``__url__``) and the sample key.
    """
    source = _source(sample)
    check_complete(sample, source)
    meta = decode_meta(sample[META_MEMBER], source)
    out: dict = {"key": str(sample.get("__key__", "?")), "meta": meta}
    for name in IMAGE_NAMES:
        if name in images and f"{name}.png" in sample:
            rgb = decode_rgb8(sample[f"{name}.png"], f"{source}: {name}.png")
            out[name] = rgb if rgb8 else unit_float_images(rgb)
    out["depth"] = torch.from_numpy(decode_depth(sample[DEPTH_MEMBER], meta["depth_unit"], source))[None]
    if VALID_MEMBER in sample:
        out["valid"] = torch.from_numpy(decode_mask(sample[VALID_MEMBER], source))[None]
        # ground truth outside the field of view is no measurement of the scene the frames show: unknown
        out["depth"] = torch.where(out["valid"], out["depth"], torch.zeros_like(out["depth"]))
    out["K"] = torch.tensor(meta["K"], dtype=torch.float32)
    out["intrinsics_known"] = torch.tensor(bool(meta["intrinsics_known"]))
    out["camera"] = torch.tensor(camera_index(meta["dataset"], source))
    for name in IMAGE_NAMES:
        pose = meta["T_world_cam"][name]
        out[f"T_{name}"] = (torch.full((4, 4), float("nan")) if pose is None
                            else torch.tensor(pose, dtype=torch.float32))
    return out


def camera_index(dataset: str, source: str) -> int:
    """The camera of a dataset's samples: its position in :data:`~endoflow.config.DATASETS`."""
    if dataset not in DATASETS:
        raise DataFormatError(source, f"meta.json names dataset {dataset!r}; expected one of {', '.join(DATASETS)}")
    return DATASETS.index(dataset)


def decode_meta(data: bytes, source: str) -> dict:
    """``meta.json`` of a sample, with the keys decoding relies on."""
    try:
        meta = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise DataFormatError(source, f"meta.json is not valid JSON: {exc}") from None
    missing = [k for k in META_KEYS if k not in meta]
    if missing:
        raise DataFormatError(source, f"meta.json lacks {missing} (format {FORMAT_VERSION} has them: shards written by "
                                      f"an older endoflow; rerun the preprocess stage)")
    return meta


def has_ground_truth(meta: Mapping, kind: str) -> bool:
    """Whether the dataset of a sample's ``meta`` has ground truth of ``kind`` (``depth`` or ``pose``)."""
    return bool(meta["ground_truth"][kind])


def decode_rgb8(data: bytes, source: str) -> torch.Tensor:
    """``[3, H, W]`` uint8 RGB from an 8-bit RGB PNG."""
    image = _decode_png(data, source)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise DataFormatError(source, f"expected 8-bit RGB, found {image.dtype} {image.shape}")
    return torch.from_numpy(np.ascontiguousarray(image[..., ::-1].transpose(2, 0, 1)))


def decode_mask(data: bytes, source: str) -> np.ndarray:
    """``H x W`` bool from an 8-bit grey ``valid.png`` (255 in, 0 out; nothing else)."""
    mask = _decode_png(data, f"{source}: {VALID_MEMBER}")
    if mask.ndim != 2 or mask.dtype != np.uint8 or not np.isin(mask, (0, 255)).all():
        raise DataFormatError(source, f"{VALID_MEMBER}: expected 8-bit grey of 0 and 255, found {mask.dtype} "
                                      f"{mask.shape}")
    return mask == 255


def decode_depth(data: bytes, depth_unit: float, source: str) -> np.ndarray:
    """``H x W`` float32 z-depth in cm (0 = unknown) from a 16-bit ``depth.png`` of ``depth_unit`` cm counts."""
    counts = _decode_png(data, f"{source}: depth.png")
    if counts.ndim != 2 or counts.dtype != np.uint16:
        raise DataFormatError(source, f"depth.png: expected 16-bit grey, found {counts.dtype} {counts.shape}")
    return counts.astype(np.float32) * np.float32(depth_unit)


def collate_samples(samples: list[dict]) -> dict:
    """Stack decoded samples: tensors gain a batch dimension; ``meta`` and ``key`` become lists."""
    batch: dict = {name: torch.stack([s[name] for s in samples]) for name in TENSOR_KEYS if name in samples[0]}
    batch["meta"] = [s["meta"] for s in samples]
    batch["key"] = [s["key"] for s in samples]
    return batch


def _decode_png(data: bytes, source: str) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DataFormatError(source, "PNG cannot be decoded")
    return image


def _source(sample: Mapping[str, object]) -> str:
    return f"{sample.get('__url__', '?')} (sample {sample.get('__key__', '?')})"
