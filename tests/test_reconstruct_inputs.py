"""`endoflow reconstruct` on inputs that used to give silent partial results: a truncated video, a model that
predicts NaN, intrinsics that cannot be the frames', frames far from square (and `--crop` to pick a part)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from endoflow.cli import main as cli
from endoflow.errors import DataFormatError
from endoflow.models.model_file import load_model_file, save_model_file
from endoflow.data.crop import Crop
from endoflow.reconstruction.frames import FrameRange, intrinsics_for, open_frames
from tests.test_reconstruct import model_file, params, recorded_rows  # noqa: F401 (fixtures)

QUICK = ["--stop", "1", "--no-fusion"]


def noise_folder(folder: Path, width: int, height: int, count: int = 2) -> Path:
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(count):
        cv2.imwrite(str(folder / f"frame_{i}.png"), rng.integers(0, 255, (height, width, 3), dtype=np.uint8))
    return folder


def truncated_video(path: Path, frames: int = 12) -> Path:
    """An MPEG-4 file with its index up front ("faststart"), cut in half: it opens and declares every frame, and
    decoding ends early without an error."""
    import av

    rng = np.random.default_rng(0)
    with av.open(str(path), "w", options={"movflags": "faststart"}) as container:
        stream = container.add_stream("mpeg4", rate=30)
        stream.width, stream.height, stream.pix_fmt = 64, 64, "yuv420p"
        for _ in range(frames):
            image = rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    return path


def test_a_truncated_video_fails_naming_the_file_and_how_many_frames_decoded(params, tmp_path: Path) -> None:
    source = open_frames(truncated_video(tmp_path / "clip.mp4"), None, params)
    assert source.length == 12
    with pytest.raises(DataFormatError, match=r"clip\.mp4: decoding ended after (\d+) of the 12 frames the video "
                                              r"declares: the file is truncated or damaged \(--stop \1 uses"):
        list(source.frames(FrameRange()))
    assert len(list(source.frames(FrameRange(stop=2)))) == 2  # the frames before the damage still serve


def test_a_model_predicting_nan_fails_naming_the_model_and_writes_nothing(
        model_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    record = load_model_file(model_file)
    name = next(key for key, value in record.state.items() if value.is_floating_point() and "depth" in key)
    record.state = {**record.state, name: torch.full_like(record.state[name], float("nan"))}
    broken = tmp_path / "nan.pt"
    save_model_file(broken, record)
    frames = noise_folder(tmp_path / "frames", 64, 64)
    assert cli(["reconstruct", str(frames), "--model", str(broken), "--out", str(tmp_path / "out"),
                "--intrinsics", "50,50,32,32", *QUICK]) == 2
    assert f"{broken}: the model predicts a depth with NaN or infinity for frame 0" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("spec, message", [
    ("1,1,32,32", r"--intrinsics 1,1,32,32: intrinsics fx=1, fy=1 give the 64x64 px frames a field of view of "
                  r"176 x 176 degrees, outside the plausible 10 to 170"),
    ("1e9,1e9,32,32", r"field of view of 3.67e-06 x 3.67e-06 degrees"),
])
def test_focal_lengths_no_camera_has_are_refused_naming_where_they_came_from(params, tmp_path: Path, spec: str,
                                                                            message: str) -> None:
    frames = open_frames(noise_folder(tmp_path / "frames", 64, 64), None, params)
    with pytest.raises(DataFormatError, match=message):
        intrinsics_for(spec, frames)


def test_a_principal_point_outside_the_square_the_model_sees_is_refused(params, tmp_path: Path) -> None:
    frames = open_frames(noise_folder(tmp_path / "frames", 128, 64), None, params)
    with pytest.raises(DataFormatError, match=r"--intrinsics 60,60,10,32: principal point cx=10, cy=32 lies outside "
                                              r"the square the model sees, 64x64 px at x=32, y=0"):
        intrinsics_for("60,60,10,32", frames)
    np.testing.assert_array_equal(intrinsics_for("60,60,10,32", frames, Crop(0, 0, 64, 64))[0], [60, 0, 10])


def test_a_side_by_side_frame_is_reconstructed_with_a_warning_and_crop_picks_a_half(
        model_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    frames = noise_folder(tmp_path / "frames", 128, 64)
    out = tmp_path / "out"
    assert cli(["reconstruct", str(frames), "--model", str(model_file), "--out", str(out),
                "--intrinsics", "60,60,64,32", *QUICK]) == 0
    assert ("frames of 128x64 px: the model sees only the centre square 64x64 px at x=32, y=0, 50% of each frame "
            "is dropped; if a frame holds two views side by side") in capsys.readouterr().err
    assert cli(["reconstruct", str(frames), "--model", str(model_file), "--out", str(out),
                "--intrinsics", "60,60,32,32", "--crop", "0,0,64,64", *QUICK]) == 0
    assert "warning" not in capsys.readouterr().err
    rows = recorded_rows(out / "recording.rrd")  # a folder has no ground truth, and fusion was off
    assert rows["/world/camera/image"] == 1 and "/world/ground_truth_path" not in rows and "/world/surface" not in rows
    summary = json.loads((out / "reconstruction.json").read_text())
    assert summary["model_view"] == {"x": 0, "y": 0, "width": 64, "height": 64}
    assert summary["K"][0][2] == pytest.approx(32)


def test_a_crop_beyond_the_frames_or_malformed_is_refused(model_file: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture) -> None:
    frames = noise_folder(tmp_path / "frames", 128, 64)
    base = ["reconstruct", str(frames), "--model", str(model_file), "--out", str(tmp_path / "out"), "--intrinsics",
            "60,60,64,32", *QUICK]
    assert cli([*base, "--crop", "64,0,128,64"]) == 2
    assert "--crop 64,0,128,64 reaches beyond the 128x64 px frames" in capsys.readouterr().err
    assert cli([*base, "--crop", "0,0,64"]) == 2
    assert "--crop: expected x,y,width,height in whole pixels" in capsys.readouterr().err


def test_a_start_beyond_the_input_and_a_negative_voxel_fail_without_a_traceback(
        model_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    frames = noise_folder(tmp_path / "frames", 64, 64)
    base = ["reconstruct", str(frames), "--model", str(model_file), "--out", str(tmp_path / "out"),
            "--intrinsics", "50,50,32,32"]
    assert cli([*base, "--start", "5"]) == 2
    assert f"2 images in {frames}: --start 5 is beyond its 2 frames (positions 0 to 1)" in capsys.readouterr().err
    assert cli([*base, "--voxel-cm", "-0.1"]) == 2
    assert "--voxel-cm must be a positive number, got -0.1" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
