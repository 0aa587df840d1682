"""Reading shards sequence by sequence: every frame of each sequence in temporal order, beside the triplet
reader of :mod:`endoflow.data.loader`.

Shards hold triplets (``prev``, ``cur``, ``next``) around target frames. A sequence's frames are its targets
(``cur``, with GT depth) plus the first target's ``prev`` and the last target's ``next`` when they are the
adjacent frames, so a reader sees the whole sequence as the SimCol3D challenge scores it. Where frames are
missing from the dataset (no triplet spans them), the frames on both sides come from the edge members and the
first frame after the gap is marked (:attr:`FrameRecord.after_gap`). Shards must hold each sequence's targets
in temporal order, as preprocessing writes a test split; anything else is refused.

The order is planned from the samples' ``meta.json`` alone (:func:`frame_sources`), and a frame is decoded from
the one member it is (:func:`read_frame`): a reader decodes each frame once, and loader processes that share a
test set's batches decode only their own (``endoflow.evaluation.evaluate``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable, Iterator, Mapping, Optional

import numpy as np
import torch

from endoflow.data.loader import raw_samples
from endoflow.data.shard_format import META_MEMBER, ShardEntry, decode_meta, decode_sample


@dataclass
class FrameRecord:
    """One frame of a sequence, in temporal order.

    Attributes:
        rgb: ``[3, H, W]`` at the stored size: ``uint8`` RGB as stored (:func:`read_frame`), or float in [0, 1] as
            the samples given to :func:`frames_in_order` hold it.
        depth_cm: ``H x W`` GT z-depth in cm, or ``None`` (edge frames from ``prev``/``next``, or no GT).
        pose: ``4 x 4`` GT ``T_world_cam`` or ``None``.
        native_size: ``(H, W)`` of the dataset's frame.
        K: ``3 x 3`` pixel intrinsics at the stored size (assumed where ``intrinsics_known`` is False).
        dataset: the dataset the frame comes from (its camera's learned intrinsics replace an assumed K).
        after_gap: frames are missing between the previous frame of the sequence and this one.
    """

    sequence: str
    group: str
    frame: int
    rgb: torch.Tensor
    depth_cm: Optional[np.ndarray]
    pose: Optional[np.ndarray]
    native_size: tuple[int, int]
    K: np.ndarray
    after_gap: bool = False
    intrinsics_known: bool = True
    dataset: str = ""


@dataclass(frozen=True)
class FrameSource:
    """Where one frame of a sequence is: member ``which`` (``prev``, ``cur`` or ``next``) of ``sample``, a decoded
    sample or, from :func:`frame_sources`, ``{"meta": parsed meta.json, "raw": the sample as read}``; ``after_gap``
    as :attr:`FrameRecord.after_gap`."""

    sample: Mapping
    which: str
    after_gap: bool = False

    @property
    def sequence(self) -> str:
        return self.sample["meta"]["sequence"]


def sequence_frames(urls: list[str], keep: Callable[[dict], bool] = lambda meta: True,
                    max_frames: Optional[int] = None) -> Iterator[FrameRecord]:
    """Every frame of every sequence in the shards ``urls`` (in their order), of the samples whose ``meta``
    ``keep`` accepts; at most ``max_frames`` targets per sequence (and their edge frames). RGB stays 8-bit."""
    return (read_frame(source) for source in frame_sources(urls, keep, max_frames))


def frame_sources(urls: list[str], keep: Callable[[dict], bool] = lambda meta: True,
                  max_frames: Optional[int] = None,
                  entries: Optional[Mapping[str, ShardEntry]] = None) -> Iterator[FrameSource]:
    """Where each frame :func:`sequence_frames` gives is, in its order, with no image decoded. Every shard is read
    whole (and so checked against its manifest ``entries``, by default the manifests beside the shards)."""
    samples = ({"meta": decode_meta(raw[META_MEMBER], _source(raw)), "raw": raw} for raw in raw_samples(urls, entries))
    return planned_frames((sample for sample in samples if keep(sample["meta"])), max_frames)


def read_frame(source: FrameSource) -> FrameRecord:
    """The frame at ``source`` (from :func:`frame_sources`), decoding its one image and the depth beside it."""
    decoded = decode_sample(source.sample["raw"], rgb8=True, images=(source.which,))
    return _record(decoded, source.which, source.after_gap)


def frames_in_order(samples: Iterable[dict], max_frames: Optional[int] = None) -> Iterator[FrameRecord]:
    """Every frame of every sequence in temporal order (see the module docstring), from ordered decoded samples."""
    return (_record(source.sample, source.which, source.after_gap) for source in planned_frames(samples, max_frames))


def planned_frames(samples: Iterable[Mapping], max_frames: Optional[int] = None) -> Iterator[FrameSource]:
    """Where every frame of every sequence is, in temporal order (see the module docstring), from ordered samples
    (each with its parsed ``meta``)."""
    last: Optional[Mapping] = None
    count = 0
    for sample in samples:
        meta = sample["meta"]
        new_sequence = last is None or meta["sequence"] != last["meta"]["sequence"]
        if new_sequence:
            if last is not None:
                yield from _edge_frame(last, "next")
            count = 0
            yield from _edge_frame(sample, "prev")
        elif meta["frame"] <= last["meta"]["frame"]:
            raise ValueError(f"sequence {meta['sequence']}: frame {meta['frame']} follows frame "
                             f"{last['meta']['frame']}; test shards must hold frames in temporal order")
        if max_frames is not None and count >= max_frames:
            continue
        count += 1
        if not new_sequence and follows_gap(last, sample):
            # no triplet spans missing frames: the frames on both sides come from the edge members
            yield from _edge_frame(last, "next")
            edge = list(_edge_frame(sample, "prev", after_gap=True))
            yield from edge
            yield FrameSource(sample, "cur", after_gap=not edge)
        else:
            yield FrameSource(sample, "cur")
        last = sample
    if last is not None:
        yield from _edge_frame(last, "next")


def follows_gap(last: Mapping, sample: Mapping) -> bool:
    """Consecutive targets of a sequence further apart than a target is from its neighbours: frames between
    them are missing from the dataset."""
    ids = sample["meta"]["frame_ids"]
    return sample["meta"]["frame"] - last["meta"]["frame"] > ids["next"] - ids["cur"]


def _edge_frame(sample: Mapping, which: str, after_gap: bool = False) -> Iterator[FrameSource]:
    ids = sample["meta"]["frame_ids"]
    if ids.get(which) is not None and abs(ids[which] - ids["cur"]) == 1:
        yield FrameSource(sample, which, after_gap)


def _source(raw: Mapping) -> str:
    return f"{raw.get('__url__', '?')} (sample {raw.get('__key__', '?')})"


def _record(sample: dict, which: str, after_gap: bool) -> FrameRecord:
    meta = sample["meta"]
    # the float64 pose from meta.json, not the float32 tensor: small rotation errors come from arccos
    listed = meta["T_world_cam"][which]
    pose = np.array(listed, dtype=np.float64) if listed is not None else None
    depth = None
    if which == "cur":
        depth = sample["depth"][0].numpy().astype(np.float32)
        depth = depth if (depth > 0).any() else None
    return FrameRecord(
        sequence=meta["sequence"], group=meta.get("group", ""), frame=int(meta["frame_ids"][which]),
        rgb=sample[which], depth_cm=depth, pose=pose if pose is not None and np.isfinite(pose).all() else None,
        native_size=(int(meta["native_size"][0]), int(meta["native_size"][1])),
        K=np.array(meta["K"], dtype=np.float64),
        after_gap=after_gap,
        intrinsics_known=bool(meta["intrinsics_known"]),
        dataset=meta["dataset"],
    )
