"""A folder of images as `endoflow reconstruct` input: `--pattern` picks the frames, a folder mixing frames with
other images (C3VD keeps depth TIFFs beside its colour frames) is refused with a listing of what it holds, and
`--threads` sets torch's thread count."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from endoflow.cli import build_parser
from endoflow.cli import main as cli
from endoflow.errors import DataFormatError
from endoflow.models.model_file import load_model_file
from endoflow.reconstruction.frames import FrameRange, open_frames
from endoflow.training.adapt import input_sequence
from tests.samples import C3VD_SAMPLE
from tests.test_reconstruct import model_file, params  # noqa: F401 (fixtures)


def c3vd_like(folder: Path, count: int = 3) -> Path:
    """C3VD's naming: colour frames ``N_color.png`` (8-bit RGB) beside ``NNNN_depth.tiff`` (16-bit, 1 channel)."""
    folder.mkdir()
    rng = np.random.default_rng(0)
    for n in range(0, 30 * count, 30):
        cv2.imwrite(str(folder / f"{n}_color.png"), rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
        cv2.imwrite(str(folder / f"{n:04d}_depth.tiff"), rng.integers(0, 65535, (48, 64), dtype=np.uint16))
    return folder


def test_frames_mixed_with_depth_maps_are_refused_listing_each_kind_and_the_pattern_to_use(
        params, tmp_path: Path) -> None:
    folder = c3vd_like(tmp_path / "seq")
    with pytest.raises(DataFormatError, match=r"seq: holds images of different kinds, frames mixed with other files: "
                                              r"3 like 0_color\.png \(64x48 px, 3 channels, 8-bit\); 3 like "
                                              r"0000_depth\.tiff \(64x48 px, 1 channel, 16-bit\); pick the frames with "
                                              r"--pattern GLOB \(--pattern '\*_color\.png'\)"):
        open_frames(folder, None, params)
    frames = open_frames(folder, None, params, "*_color.png")
    assert [f.index for f in frames.frames(FrameRange())] == [0, 1, 2] and frames.native_size == (48, 64)
    assert [p.name for p in frames.files] == ["0_color.png", "30_color.png", "60_color.png"]


def test_a_pattern_that_matches_nothing_or_is_given_for_a_video_says_so(params, tmp_path: Path) -> None:
    folder = c3vd_like(tmp_path / "seq")
    with pytest.raises(DataFormatError, match=r"no image matches --pattern '\*\.jpg'; it holds 6 images, such as "
                                              r"0_color\.png, 0000_depth\.tiff, 30_color\.png"):
        open_frames(folder, None, params, "*.jpg")
    (tmp_path / "clip.mp4").write_bytes(b"")
    with pytest.raises(DataFormatError, match="--pattern '\\*.png' picks images of a folder; this input is not one"):
        open_frames(tmp_path / "clip.mp4", None, params, "*.png")


@pytest.mark.skipif(not C3VD_SAMPLE.is_dir(), reason=f"real C3VD sample not found at {C3VD_SAMPLE}")
def test_the_real_c3vd_layout_is_refused_without_a_pattern_and_read_with_one(params) -> None:
    folder = C3VD_SAMPLE / "cecum_t1_a"
    with pytest.raises(DataFormatError, match=r"10 like 0_color\.png \(1350x1080 px, 3 channels, 8-bit\); 10 like "
                                              r"0000_depth\.tiff \(1350x1080 px, 1 channel, 16-bit\)"):
        open_frames(folder, None, params)
    frames = open_frames(folder, None, params, "*_color.png")
    assert frames.length == 10 and frames.native_size == (1080, 1350)
    assert frames.files[1].name == "30_color.png"  # natural order: 30 before 120


def test_the_fit_reads_the_frames_the_pattern_picks_as_reconstruct_does(params, model_file: Path,
                                                                         tmp_path: Path) -> None:
    """`adapt --pattern` and `reconstruct --adapt --pattern`: the fit trains on the colour frames alone (before, it
    read the whole folder: refused, or the wrong images where they were of one kind)."""
    folder = c3vd_like(tmp_path / "seq", count=6)
    sequence = input_sequence(folder, None, params, pattern="*_color.png")
    assert [Path(files[0]).name for files in sequence.source_files] == [f"{n}_color.png" for n in range(0, 180, 30)]
    assert sequence.load_rgb(0).shape == (48, 64, 3)
    with pytest.raises(DataFormatError, match="holds images of different kinds"):
        input_sequence(folder, None, params)
    with pytest.raises(DataFormatError, match=r"--pattern '\*_color\.png' picks images of a folder, not a dataset"):
        input_sequence(folder, "S1", params, pattern="*_color.png")
    (tmp_path / "clip.mp4").write_bytes(b"")
    with pytest.raises(DataFormatError, match=r"clip\.mp4: --pattern '\*\.png' picks images of a folder; this input"):
        input_sequence(tmp_path / "clip.mp4", None, params, pattern="*.png")
    # both commands fit through one function (cli._run_adaptation), which reads args.pattern
    assert build_parser().parse_args(["adapt", str(folder), "--pattern", "*_color.png", "--out", "a.pt"]).pattern \
        == "*_color.png"
    assert cli(["reconstruct", str(folder), "--pattern", "*_color.png", "--adapt", "1", "--model", str(model_file),
                "--out", str(tmp_path / "out"), "--intrinsics", "40,40,32,24", "--no-fusion", "--threads", "1"]) == 0
    summary = json.loads((tmp_path / "out" / "reconstruction.json").read_text())
    assert summary["frames"] == 6 and summary["adaptation"]["steps"] == 1
    assert load_model_file(model_file).adapted_from is None  # what was fitted is a copy


def test_threads_sets_torchs_thread_count_and_the_summary_records_it(model_file: Path, tmp_path: Path) -> None:
    folder = c3vd_like(tmp_path / "seq", count=1)
    before = torch.get_num_threads()
    try:
        assert cli(["reconstruct", str(folder), "--pattern", "*_color.png", "--model", str(model_file), "--out",
                    str(tmp_path / "out"), "--intrinsics", "40,40,32,24", "--no-fusion", "--threads", "1"]) == 0
        assert json.loads((tmp_path / "out" / "reconstruction.json").read_text())["threads"] == 1
    finally:
        torch.set_num_threads(before)
    with pytest.raises(SystemExit):
        cli(["reconstruct", str(folder), "--out", str(tmp_path / "o"), "--threads", "0"])
