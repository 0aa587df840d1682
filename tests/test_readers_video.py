"""Unlabelled video as a dataset: a folder of videos and frame folders becomes sequences, then shards that say they
have no ground truth; the real colonoscopy clip reads as a user would point at it."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from endoflow.config import Params, params_from_dict
from endoflow.data.loader import raw_samples
from endoflow.data.registry import detect_dataset, open_reader
from endoflow.data.shard_format import decode_sample, has_ground_truth
from endoflow.data.shard_engines import native_thread_count, pool_context
from endoflow.data.shards import preprocess_dataset
from endoflow.data.intrinsics import assumed_intrinsics
from endoflow.data.video import VAL_SUFFIX, VideoFile, frame_stride
from endoflow.data.video_encoding import write_video
from endoflow.errors import DataFormatError
from endoflow.reconstruction.frames import FrameRange, VideoFrames, open_frames
from endoflow.reconstruction.streams import decoded_ahead
from tests.samples import COLONOSCOPY_CLIP

SIZE = 48
needs_clip = pytest.mark.skipif(not COLONOSCOPY_CLIP.is_file(), reason=f"real colonoscopy clip not found at "
                                                                       f"{COLONOSCOPY_CLIP}")


def moving_frames(count: int, seed: int = 0, size: int = SIZE) -> list[np.ndarray]:
    """Frames of a texture sliding right one pixel a frame, seen through a circle (black corners)."""
    texture = cv2.GaussianBlur(np.random.default_rng(seed).integers(30, 230, (size, size + count, 3)).astype(np.uint8),
                               (5, 5), 0)
    v, u = np.mgrid[:size, :size]
    inside = ((u - (size - 1) / 2) ** 2 + (v - (size - 1) / 2) ** 2 <= (0.55 * size) ** 2)[..., None]
    return [np.ascontiguousarray(texture[:, i:i + size]) * inside.astype(np.uint8) for i in range(count)]


def video_root(root: Path, frames: int = 20) -> Path:
    """``clip_a.mp4`` (30 fps) and ``clip_b/`` (PNG frames), as the built-in video is written."""
    root.mkdir(parents=True, exist_ok=True)
    write_video(root / "clip_a.mp4", moving_frames(frames), 30.0)
    (root / "clip_b").mkdir()
    for i, rgb in enumerate(moving_frames(frames, seed=1)):
        cv2.imwrite(str(root / "clip_b" / f"frame_{i}.png"), rgb[..., ::-1])
    return root


def video_params(**settings) -> Params:
    return params_from_dict({"data": {"size": 32, "video": settings},
                             "preprocess": {"samples_per_shard": 4, "shard_multiple": 1, "workers": 1}})


def test_every_video_and_frame_folder_is_a_sequence_with_its_last_fifth_held_out(tmp_path: Path):
    root = video_root(tmp_path / "videos")
    assert detect_dataset(root) == "video"
    sequences = open_reader(root, None, video_params()).sequences()
    assert [(s.name, s.split, len(s)) for s in sequences] == [
        ("clip_a", "train", 16), (f"clip_a{VAL_SUFFIX}", "val", 4), ("clip_b", "train", 16),
        (f"clip_b{VAL_SUFFIX}", "val", 4)]
    held_out = sequences[3]
    assert held_out.frame_ids == [16, 17, 18, 19] and held_out.poses is None and held_out.load_depth is None
    # the frames are the folder's own, in order: the held-out part continues where training stops
    np.testing.assert_array_equal(held_out.load_rgb(0), moving_frames(20, seed=1)[16])
    # and the video's, through its lossy compression: of the frames around it, the nearest is the one it is
    decoded = sequences[1].load_rgb(0).astype(float)
    errors = [np.abs(decoded - frame).mean() for frame in moving_frames(20)[14:19]]
    assert int(np.argmin(errors)) == 2


def test_named_sequences_go_to_their_split_whole_and_unknown_names_are_refused(tmp_path: Path):
    root = video_root(tmp_path / "videos")
    sequences = open_reader(root, None, video_params(test=["clip_b"], val_share=0.0)).sequences()
    assert [(s.name, s.split, len(s)) for s in sequences] == [("clip_a", "train", 20), ("clip_b", "test", 20)]
    with pytest.raises(DataFormatError, match="lists sequence 'clip_c', which is not here"):
        open_reader(root, None, video_params(val=["clip_c"])).sequences()


def test_a_target_frame_rate_keeps_every_nth_frame_and_a_crop_cuts_every_frame(tmp_path: Path):
    root = video_root(tmp_path / "videos")
    params = video_params(fps=10, folder_fps=30, crop=[4, 2, 40, 44], val_share=0.0)
    (_, sequence) = open_reader(root, None, params).sequences()
    assert sequence.frame_ids == [0, 3, 6, 9, 12, 15, 18] and sequence.image_size == (44, 40)
    np.testing.assert_array_equal(sequence.load_rgb(2), moving_frames(20, seed=1)[6][2:46, 4:44])
    assert frame_stride(30, None) == frame_stride(30, 60) == 1 and frame_stride(25, 10) == 2
    with pytest.raises(DataFormatError, match=r"--crop 40,2,40,44 reaches beyond the 48x48 px frames"):
        open_reader(root, None, video_params(crop=[40, 2, 40, 44])).sequences()


def test_intrinsics_come_from_a_sidecar_then_params_else_are_assumed_and_say_so(tmp_path: Path):
    root = video_root(tmp_path / "videos")
    (root / "clip_b.intrinsics.yaml").write_text("fx: 40\nfy: 41\ncx: 23.5\ncy: 24\nwidth: 48\nheight: 48\n")
    by_name = {s.name: s for s in open_reader(root, None, video_params(crop=[4, 0, 44, 48])).sequences()}
    assert not by_name["clip_a"].intrinsics_known and by_name["clip_b"].intrinsics_known
    np.testing.assert_allclose(by_name["clip_b"].K, [[40, 0, 19.5], [0, 41, 24], [0, 0, 1]])  # cropped: cx - 4
    np.testing.assert_allclose(by_name["clip_a"].K, assumed_intrinsics((48, 44), 140.0))
    given = {s.name: s for s in open_reader(root, None, video_params(intrinsics="30,30,23.5,23.5")).sequences()}
    assert given["clip_a"].intrinsics_known and given["clip_a"].K[0, 0] == 30 and given["clip_b"].K[0, 0] == 40
    # a 140-degree diagonal: the corner's ray is 70 degrees off the axis
    K = assumed_intrinsics((48, 64), 140.0)
    assert np.degrees(np.arctan(np.hypot(32, 24) / K[0, 0])) == pytest.approx(70.0)


def test_frames_are_the_same_read_in_any_order_as_decoded_in_sequence(tmp_path: Path):
    root = video_root(tmp_path / "videos", frames=60)
    video = VideoFile(root / "clip_a.mp4")
    in_order = [frame.rgb for frame in VideoFrames(root / "clip_a.mp4").frames(FrameRange())]
    assert len(video) == len(in_order) == 60
    for index in (59, 3, 4, 40, 0, 41, 2):
        np.testing.assert_array_equal(video(index), in_order[index])


def test_a_video_sequences_frames_decoded_side_by_side_are_its_frames_in_order(tmp_path: Path):
    root = video_root(tmp_path / "videos", frames=60)
    in_order = [frame.rgb for frame in open_frames(root, "clip_a", video_params()).frames(FrameRange())]
    # four threads share the sequence's one decoder (reconstruct's reading on 16 cores)
    readers = open_frames(root, "clip_a", video_params()).readers(FrameRange())
    side_by_side = [frame.rgb for frame in decoded_ahead(readers, count=8, workers=4)]
    assert len(side_by_side) == len(in_order) == 48
    for together, alone in zip(side_by_side, in_order):
        np.testing.assert_array_equal(together, alone)


def test_shards_of_video_have_no_ground_truth_and_say_so(tmp_path: Path):
    root = video_root(tmp_path / "videos")
    params = video_params(root=str(root))
    summary = preprocess_dataset("video", params, tmp_path / "shards")
    assert summary["samples"] == {"train": 2 * 14, "val": 2 * 2, "test": 0}
    samples = [decode_sample(raw) for raw in raw_samples(sorted(str(p) for p in (tmp_path / "shards").glob("*.tar")))]
    for sample in samples:
        meta = sample["meta"]
        assert not has_ground_truth(meta, "depth") and not has_ground_truth(meta, "pose")
        assert meta["intrinsics_known"] is False  # no sidecar, nothing in params
        assert (sample["depth"] == 0).all() and all(meta["T_world_cam"][k] is None for k in ("prev", "cur", "next"))
        assert not sample["valid"][0, 0, 0] and sample["valid"][0, 16, 16]  # the circle's black corners


def test_bad_video_input_is_refused_naming_the_file(tmp_path: Path):
    root = video_root(tmp_path / "videos")
    (root / "clip_a").mkdir()
    cv2.imwrite(str(root / "clip_a" / "0.png"), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(DataFormatError, match="clip_a.*names the same sequence as"):
        open_reader(root, "video", Params()).sequences()
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "clip.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42 not really a video")
    with pytest.raises(DataFormatError, match=r"clip.mp4: cannot be read as a video"):
        open_reader(broken, "video", Params()).sequences()
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataFormatError, match="no known dataset layout"):
        detect_dataset(empty)
    with pytest.raises(DataFormatError, match="no videos .* or folders of images found"):
        open_reader(empty, "video", Params()).sequences()


def test_a_video_cut_short_names_the_frame_it_cannot_reach(tmp_path: Path):
    path = tmp_path / "videos" / "clip.mp4"
    path.parent.mkdir()
    write_video(path, moving_frames(60), 30.0)
    video = VideoFile(path)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])  # the file is damaged after it was listed
    with pytest.raises(DataFormatError, match=r"clip.mp4: frame 59 of the 60 it lists cannot be decoded"):
        video(59)


@needs_clip
def test_the_real_clip_reads_as_a_user_points_at_it(tmp_path: Path):
    (tmp_path / "clip").mkdir()
    (tmp_path / "clip" / "colonoscopy.mp4").symlink_to(COLONOSCOPY_CLIP)
    sequences = open_reader(tmp_path / "clip", None, video_params(crop=[0, 0, 192, 192])).sequences()
    assert [(s.name, s.split, len(s), s.image_size) for s in sequences] == [
        ("colonoscopy", "train", 480, (192, 192)), (f"colonoscopy{VAL_SUFFIX}", "val", 120, (192, 192))]
    train = sequences[0]
    assert not train.intrinsics_known and train.load_rgb(479).shape == (192, 192, 3)
    assert 0.85 < train.field_of_view().mean() < 0.97  # the circle, its four corners out


def test_a_pool_of_workers_writes_the_shards_one_process_writes_after_ffmpeg_started_its_threads(tmp_path: Path):
    """Finding the field of view decodes frames here first; FFmpeg's decoder threads (it starts them for frames this
    large) must not be inherited by forked workers, which would wait forever on a lock one of them held."""
    root = tmp_path / "videos"
    root.mkdir()
    write_video(root / "clip_a.mp4", moving_frames(12, size=480), 30.0)
    video = VideoFile(root / "clip_a.mp4")
    before = native_thread_count()
    video(0)
    assert native_thread_count() > before and pool_context().get_start_method() != "fork"
    written = {}
    for workers in (1, 2):
        params = video_params(root=str(root))
        params.preprocess.workers = workers
        preprocess_dataset("video", params, tmp_path / f"shards_{workers}")
        written[workers] = {p.name: p.read_bytes() for p in (tmp_path / f"shards_{workers}").iterdir()}
    assert written[1] == written[2] and len(written[1]) > 2
