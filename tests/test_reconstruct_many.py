"""`endoflow reconstruct` over many videos. On the simulated two-node Ray cluster of tests/test_preprocess_ray.py, a
folder of videos gives one folder per video, each with the bytes `endoflow reconstruct` of that video alone writes;
a damaged video is named with its error and the others are kept; a rerun keeps the folders done with the same
settings. Without Ray: which inputs are many videos, the refusals before any work, and what the resume key covers
(what decides which videos a rerun does again)."""

from __future__ import annotations

import io
import os
import re
import sys
from contextlib import redirect_stderr
from dataclasses import replace
from pathlib import Path

import pytest
import ray
import yaml

from endoflow.cli import main as cli
from endoflow.config import Params, params_to_dict
from endoflow.data.video_encoding import write_video
from endoflow.errors import DataFormatError
from endoflow.reconstruction.frames import FrameRange
from endoflow.reconstruction.many import ManySettings, holds_videos, lines_named, resume_key, video_files
from endoflow.reconstruction.reconstruct import ReconstructOptions
from tests.test_preprocess_ray import cluster  # noqa: F401 (fixture: a head and a second node, one CPU each)
from tests.test_readers_video import moving_frames
from tests.test_reconstruct import model_file, params  # noqa: F401 (fixtures)

FRAMES = 6
# what every reconstruction folder holds (and 6 depth maps); the same bytes as a video reconstructed alone: the
# depth and the paths (the pictures and the recording are drawn from them, video.mp4's encoder may differ)
EXPECTED = {"reconstruction.json", "trajectory.tum", "trajectory_network.tum", "trajectory.kitti", "mesh.ply",
            "points.ply", "sheet.png", "video.mp4", "recording.rrd", "depth", "preview", "simcol"}
SAME_BYTES = ("trajectory.tum", "trajectory_network.tum", "trajectory.kitti", "mesh.ply",
              *(f"depth/{i:06d}.png" for i in range(FRAMES)))


def clip(path: Path, seed: int) -> Path:
    write_video(path, moving_frames(FRAMES, seed=seed, size=64), 30.0)
    return path


@pytest.mark.slow
def test_a_folder_of_videos_on_two_nodes_gives_a_folder_each_names_the_damaged_one_and_a_rerun_does_the_rest(
        cluster, model_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    videos = tmp_path / "clinic"
    videos.mkdir()
    clip(videos / "clip_a.mp4", 0), clip(videos / "clip_b.mp4", 1)
    (videos / "damaged.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42 not really a video" * 20)
    params_file = tmp_path / "params.yaml"
    params = Params()
    params.ray = params.ray.replace(address=cluster.address)
    params_file.write_text(yaml.safe_dump(params_to_dict(params)))
    out = tmp_path / "recon"
    command = ["--params", str(params_file), "reconstruct", str(videos), "--model", str(model_file), "--out",
               str(out), "--threads", "1"]

    assert cli([*command[:-1], "2"]) == 2  # --threads 2: no node of one CPU holds a task, Ray would wait forever
    assert re.search(r"each video's Ray task reserves 2 CPUs \(--threads; default: the model's threads\), and no "
                     r"node of the Ray cluster has them \(largest: 1 CPUs", capsys.readouterr().err)
    assert not out.exists() and not ray.is_initialized()

    assert cli(command) == 1
    printed = capsys.readouterr()
    assert f"3 videos into {out}: 2 reconstructed ({2 * FRAMES} frames), 0 kept from an earlier run, 1 failed" \
        in printed.out
    assert re.search(rf"failed: {re.escape(str(videos / 'damaged.mp4'))}: cannot be read as a video", printed.out)
    assert "1 of 3 videos failed" in printed.err and not ray.is_initialized()
    assert sorted(os.listdir(out)) == ["clip_a", "clip_b"]  # no folder for the damaged video, nothing staged left
    for name in ("clip_a", "clip_b"):
        assert EXPECTED <= set(os.listdir(out / name))
        assert len(list((out / name / "depth").glob("*.png"))) == FRAMES

    alone = tmp_path / "alone"
    assert cli(["--params", str(params_file), "reconstruct", str(videos / "clip_a.mp4"), "--model",
                str(model_file), "--out", str(alone), "--threads", "1"]) == 0
    assert [file for file in SAME_BYTES if (out / "clip_a" / file).read_bytes() != (alone / file).read_bytes()] == []

    written = {name: (out / name / "reconstruction.json").stat().st_mtime_ns for name in ("clip_a", "clip_b")}
    (videos / "damaged.mp4").unlink()  # the rerun has nothing left to do: it keeps both and starts no Ray
    capsys.readouterr()
    assert cli(command) == 0
    printed = capsys.readouterr()
    assert f"2 videos into {out}: 0 reconstructed (0 frames), 2 kept from an earlier run, 0 failed" in printed.out
    assert cluster.address not in printed.err  # it did not join the cluster
    assert {name: (out / name / "reconstruction.json").stat().st_mtime_ns for name in written} == written


def test_inputs_are_many_videos_when_several_or_a_folder_of_videos(tmp_path: Path) -> None:
    clinic = tmp_path / "clinic"
    clinic.mkdir()
    for name in ("clip_10.mp4", "clip_2.MOV", "._clip_2.mp4", "notes.txt"):  # ._*: a macOS copy's metadata
        (clinic / name).write_bytes(b"")
    (clinic / "frames").mkdir()  # sub-folders are not looked into
    (clinic / "frames" / "frame_0.png").write_bytes(b"")
    assert holds_videos(clinic) and not holds_videos(clinic / "frames") and not holds_videos(clinic / "clip_10.mp4")
    assert video_files([clinic]) == [clinic / "clip_2.MOV", clinic / "clip_10.mp4"]
    assert video_files([clinic / "clip_10.mp4", clinic]) == [clinic / "clip_10.mp4", clinic / "clip_2.MOV"]
    with pytest.raises(DataFormatError, match=r"frames: holds no video files .*a folder of images is the frames of "
                                              r"one video: reconstruct it on its own"):
        video_files([clinic, clinic / "frames"])
    (clinic / "frame_0.png").write_bytes(b"")
    with pytest.raises(DataFormatError, match=r"clinic: holds both videos \(2, such as clip_2.MOV\) and images "
                                              r"\(1, such as frame_0.png\).*pick the frames with --pattern"):
        video_files([clinic])
    with pytest.raises(DataFormatError, match=r"notes.txt: is not a video file \(expected .mp4"):
        video_files([clinic / "clip_10.mp4", clinic / "notes.txt"])
    with pytest.raises(FileNotFoundError, match=r"missing.mp4: no such video or folder of videos"):
        video_files([clinic / "clip_10.mp4", clinic / "missing.mp4"])


def test_what_cannot_run_is_refused_before_any_work(model_file: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture) -> None:
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "Clip.mp4").write_bytes(b"")
    (tmp_path / "b" / "clip.mp4").write_bytes(b"")
    out = tmp_path / "recon"
    model = ["--model", str(model_file), "--out", str(out)]
    refusals = {
        (str(tmp_path / "a"), str(tmp_path / "b")):
            rf"recon: videos of one name would share an output folder \({re.escape(str(tmp_path / 'a' / 'Clip.mp4'))}"
            rf" and [^;]+; rename them",
        (str(tmp_path / "a"), "--device", "cuda:1"): r"--device cuda:1: each video's Ray task is given a GPU of its "
                                                      r"own where it needs one; use auto, cpu, cuda",
        (str(tmp_path / "a"), str(tmp_path / "b" / "clip.mp4"), "--sequence", "S1"): r"--sequence takes one input",
    }
    for arguments, message in refusals.items():
        assert cli(["reconstruct", *arguments, *model]) == 2
        assert re.search(message, capsys.readouterr().err), arguments
    (out / "Clip").mkdir(parents=True)
    (out / "Clip" / "notes.txt").write_text("mine")
    assert cli(["reconstruct", str(tmp_path / "a"), *model]) == 2
    assert "recon/Clip: will not replace a folder that is not an earlier endoflow reconstruction" \
        in capsys.readouterr().err
    assert (out / "Clip" / "notes.txt").read_text() == "mine" and not ray.is_initialized()


def test_the_resume_key_follows_the_video_the_model_the_intrinsics_and_every_option_but_force(
        tmp_path: Path) -> None:
    video = tmp_path / "clip.mp4"
    video.write_bytes(b"frames")
    settings = ManySettings(tmp_path / "model.pt", None, ReconstructOptions(), 1)
    key = resume_key(video, settings, "sha-of-the-model")
    assert resume_key(video, replace(settings, options=ReconstructOptions(force=True)), "sha-of-the-model") == key
    changed = [resume_key(video, replace(settings, options=ReconstructOptions(frames=FrameRange(stride=2))),
                          "sha-of-the-model"),
               resume_key(video, replace(settings, threads=2), "sha-of-the-model"),
               resume_key(video, replace(settings, intrinsics="50,50,32,32"), "sha-of-the-model"),
               resume_key(video, settings, "sha-of-another-model")]
    os.utime(video, ns=(0, 0))
    changed.append(resume_key(video, settings, "sha-of-the-model"))
    assert len({key, *changed}) == 6


def test_a_tasks_lines_are_named_after_its_video() -> None:
    caught = io.StringIO()
    with redirect_stderr(caught), lines_named("clip.mp4"):
        print("intrinsics: assumed\n6/6 frames", file=sys.stderr)
        sys.stderr.write("a last line without its newline")
    assert caught.getvalue() == ("clip.mp4: intrinsics: assumed\nclip.mp4: 6/6 frames\n"
                                 "clip.mp4: a last line without its newline\n")
