"""Shard tar writing: ``webdataset.TarWriter`` through an 8 MiB file buffer, alone and as preprocessing uses
it (also hashing the file and every sample for the manifest), vs the former hand-written ``tarfile`` loop
(which hashed nothing).

All three write the same samples (member bytes of the stored size, PNG-like incompressible payloads) with fixed
metadata, in one run, best of ``--repeats``; prints MB/s of each and the ratio. The shard format took
``TarWriter`` on the condition that it is not slower (issue 9).

    python benchmarks/bench_tar_writer.py [--samples 256] [--size 480] [--repeats 5]
"""

from __future__ import annotations

import argparse
import io
import os
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np
import webdataset as wds

from endoflow.data.shard_format import HashingWriter, sample_sha256
from endoflow.data.shard_writer import WRITE_BUFFER


def samples(count: int, size: int) -> list[dict]:
    rng = np.random.default_rng(0)
    rgb = [rng.integers(0, 256, size * size * 3 // 2, dtype=np.uint8).tobytes() for _ in range(3)]
    depth = rng.integers(0, 256, size * size, dtype=np.uint8).tobytes()
    meta = b'{"dataset": "simcol"}' * 20
    return [{"__key__": f"simcol-S1-{i:06d}", "prev.png": rgb[0], "cur.png": rgb[1], "next.png": rgb[2],
             "depth.png": depth, "meta.json": meta} for i in range(count)]


def write_with_tarwriter(path: Path, items: list[dict]) -> None:
    with open(path, "wb", buffering=WRITE_BUFFER) as stream:
        with wds.TarWriter(stream, encoder=False, mtime=0, user="", group="") as tar:
            for item in items:
                tar.write(item)


def write_as_preprocessing(path: Path, items: list[dict]) -> None:
    with open(path, "wb", buffering=WRITE_BUFFER) as stream:
        with wds.TarWriter(HashingWriter(stream), encoder=False, mtime=0, user="", group="") as tar:
            for item in items:
                tar.write(item)
                sample_sha256(item)


def write_by_hand(path: Path, items: list[dict]) -> None:
    with tarfile.open(path, "w", format=tarfile.PAX_FORMAT) as tar:
        for item in items:
            for name in sorted(k for k in item if k != "__key__"):
                info = tarfile.TarInfo(f"{item['__key__']}.{name}")
                info.size, info.mode, info.mtime = len(item[name]), 0o444, 0
                tar.addfile(info, io.BytesIO(item[name]))


def best_seconds(write, path: Path, items: list[dict], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        write(path, items)
        with open(path, "rb+") as f:
            os.fsync(f.fileno())
        times.append(time.perf_counter() - started)
        path.unlink()
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=256)
    parser.add_argument("--size", type=int, default=480)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    items = samples(args.samples, args.size)
    megabytes = sum(len(v) for item in items for k, v in item.items() if k != "__key__") / 1e6
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "shard.tar"
        wds_s = best_seconds(write_with_tarwriter, path, items, args.repeats)
        hashed_s = best_seconds(write_as_preprocessing, path, items, args.repeats)
        hand_s = best_seconds(write_by_hand, path, items, args.repeats)
    print(f"{args.samples} samples at {args.size} px, {megabytes:.0f} MB per shard, best of {args.repeats}")
    print(f"  webdataset.TarWriter             : {megabytes / wds_s:8.1f} MB/s")
    print(f"  TarWriter + SHA-256s (preprocess) : {megabytes / hashed_s:8.1f} MB/s")
    print(f"  hand-written tarfile (former)    : {megabytes / hand_s:8.1f} MB/s")
    print(f"  ratio TarWriter / hand-written throughput: {hand_s / wds_s:.2f}")
    print(f"  ratio preprocessing's writer / hand-written throughput: {hand_s / hashed_s:.2f}")


if __name__ == "__main__":
    main()
