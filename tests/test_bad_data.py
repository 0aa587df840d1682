"""Data that is wrong but decodable: NaN / inf in pose files, frames missing inside a sequence.

Neither may pass silently: the reader warns and lists it in the sequence's problems (so ``data inspect``
shows it), ``data check`` counts the frames it skips, and preprocessing never writes a non-finite pose nor a
sample whose neighbours span a gap. Also: a synthetic sequence rendered twice at once stays whole.
"""

from __future__ import annotations

import json
import tarfile
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from endoflow.config import Params
from endoflow.data.base import Sequence, missing_frame_ids
from endoflow.data.check import check_dataset, check_sequence, format_check
from endoflow.data.inspect import format_inspection, inspect_dataset
from endoflow.data.registry import open_reader
from endoflow.data.shard_plan import EncodeSettings, sequence_samples
from endoflow.data.shards import preprocess_dataset
from endoflow.synth import writers
from endoflow.synth.writers import plan_jobs, render_job
from tests.fixtures_native import (
    preprocess_params,
    remove_simcol_frame,
    replace_line,
    write_endoslam_camera,
    write_endoslam_unitycam,
    write_simcol,
)

S1 = "SyntheticColon_I"


def read_sequences(root: Path, dataset: str = "simcol") -> tuple[dict[str, Sequence], list[str]]:
    """The sequences under ``root`` by name, and the warnings the reader gave."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sequences = open_reader(root, dataset, Params()).sequences()
    return {s.name: s for s in sequences}, [str(w.message) for w in caught]


def shard_metas(out_dir: Path) -> list[dict]:
    metas = []
    for shard in sorted(out_dir.glob("*.tar")):
        with tarfile.open(shard) as tar:
            metas += [json.load(tar.extractfile(m)) for m in tar.getmembers() if m.name.endswith(".meta.json")]
    return metas


# --------------------------------------------------------------------------------- NaN and inf poses
@pytest.fixture
def simcol_with_bad_poses(tmp_path: Path) -> Path:
    """S1 with 6 frames: NaN position for frame 2, infinite quaternion component for frame 4."""
    root = tmp_path / "simcol"
    write_simcol(root, frames=6, size=16)
    replace_line(root / S1 / "SavedPosition_S1.txt", 2, "nan nan nan")
    replace_line(root / S1 / "SavedRotationQuaternion_S1.txt", 4, "0.1 inf 0.2 0.9")
    return root


def test_reader_warns_naming_the_pose_file_and_frames_and_drops_those_poses(simcol_with_bad_poses: Path) -> None:
    sequences, warned = read_sequences(simcol_with_bad_poses)
    s1 = sequences["S1"]
    assert [s1.pose(i) is None for i in range(6)] == [False, False, True, False, True, False]
    assert np.isnan(s1.poses[[2, 4]]).all()  # the whole pose, not only the entries the bad value reached
    for file, frame in (("SavedPosition_S1.txt", "(2)"), ("SavedRotationQuaternion_S1.txt", "(4)")):
        assert any(file in w and "non-finite" in w and frame in w for w in warned)
        assert any(p.startswith(file) and frame in p for p in s1.problems)
    assert sequences["S4"].problems == []


def test_inspect_reports_non_finite_poses_as_problems(simcol_with_bad_poses: Path) -> None:
    report = inspect_dataset(simcol_with_bad_poses, None, Params())
    entry = next(e for e in report["sequences"] if e["name"] == "S1")
    assert entry["poses"]["known"] == 4 and entry["poses"]["unknown"] == [2, 4]
    text = format_inspection(report)
    s1_text = text[text.index("S1  [") : text.index("S4  [")]
    assert "problems: none" not in s1_text
    assert "SavedPosition_S1.txt: non-finite pose values (NaN or inf) for 1 frame(s) (2)" in s1_text
    assert "unknown: frames 2, 4" in s1_text


def test_check_skips_frames_without_a_valid_pose_and_counts_them(simcol_with_bad_poses: Path) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        report = check_dataset(simcol_with_bad_poses, None, Params())
    by_name = {entry["name"]: entry for entry in report["sequences"]}
    assert by_name["S1"]["frames_without_pose"] == 2 and by_name["S4"]["frames_without_pose"] == 0
    # targets 0, 1, 3, 5; neighbours 2 and 4 are skipped: 0-1, 1-0, 3 has none, 5 has none
    assert by_name["S1"]["pairs"] == 2
    assert "2 frame(s) without a valid pose skipped" in format_check(report)


def test_preprocess_keeps_the_samples_with_a_null_pose_and_counts_them(
    simcol_with_bad_poses: Path, tmp_path: Path
) -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = preprocess_dataset("simcol", preprocess_params("simcol", simcol_with_bad_poses), tmp_path / "out")
    assert any("SavedPosition_S1.txt" in str(w.message) for w in caught)
    # S1's targets 1..4 all read frame 2 or 4
    assert summary["samples_without_pose"] == 4
    metas = {m["frame"]: m for m in shard_metas(tmp_path / "out") if m["sequence"] == "S1"}
    assert sorted(metas) == [1, 2, 3, 4]
    assert metas[2]["T_world_cam"]["cur"] is None and metas[1]["T_world_cam"]["next"] is None
    assert metas[1]["T_world_cam"]["cur"] is not None
    for meta in shard_metas(tmp_path / "out"):
        for pose in meta["T_world_cam"].values():
            assert pose is None or np.isfinite(pose).all()


def test_unitycam_row_with_inf_is_dropped_and_named(tmp_path: Path) -> None:
    write_endoslam_unitycam(tmp_path, frames=8)
    csv = tmp_path / "UnityCam" / "Colon" / "Poses" / "colon_position_rotation.csv"
    row = csv.read_text().splitlines()[3].split(",")
    row[1] = "inf"
    replace_line(csv, 3, ",".join(row))
    sequences, warned = read_sequences(tmp_path, "endoslam")
    notes = " | ".join(sequences["UnityCam/Colon"].problems)
    assert "dropped 1 row(s) with missing values" in notes and "data row(s) 3)" in notes
    assert any("data row(s) 3)" in w for w in warned)


def test_camera_sheet_row_with_inf_is_dropped_not_read_as_a_pose(tmp_path: Path) -> None:
    write_endoslam_camera(tmp_path, frames=4)
    sheet = next((tmp_path / "Cameras").rglob("poses.xlsx"))
    table = pd.read_excel(sheet, engine="openpyxl")
    table.loc[table["ImageFrame"] == 1, "trans_y"] = np.inf
    table.to_excel(sheet, index=False, engine="openpyxl")
    params = Params()
    params.data.endoslam.intrinsics = [[30.0, 0.0, 16.0], [0.0, 30.0, 12.0], [0.0, 0.0, 1.0]]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        (sequence,) = open_reader(tmp_path, "endoslam", params).sequences()
    assert sequence.pose(1) is None and sequence.pose(0) is not None
    assert any("dropped 1 row(s) with missing values" in p for p in sequence.problems)
    assert any("dropped 1 row(s)" in str(w.message) for w in caught)


# ------------------------------------------------------------------------------------ frame gaps
@pytest.fixture
def simcol_with_a_gap(tmp_path: Path) -> Path:
    """S1 with frames 0..7 but 4 missing; S4 and O1 whole."""
    root = tmp_path / "simcol"
    write_simcol(root, frames=8, size=16)
    remove_simcol_frame(root / S1, "S1", 4)
    return root


def test_a_missing_frame_is_warned_once_naming_the_sequence_and_the_frame(simcol_with_a_gap: Path) -> None:
    sequences, warned = read_sequences(simcol_with_a_gap)
    gap_warnings = [w for w in warned if "not contiguous" in w]
    assert len(gap_warnings) == 1
    assert "sequence S1" in gap_warnings[0] and "1 missing (4)" in gap_warnings[0]
    assert sequences["S1"].frame_ids == [0, 1, 2, 3, 5, 6, 7]
    assert sequences["S4"].problems == []


def test_inspect_reports_the_gap(simcol_with_a_gap: Path) -> None:
    report = inspect_dataset(simcol_with_a_gap, None, Params())
    entry = next(e for e in report["sequences"] if e["name"] == "S1")
    assert any("not contiguous" in p and "(4)" in p for p in entry["problems"])
    assert "1 missing (4)" in format_inspection(report)


def test_preprocess_builds_no_sample_across_the_gap(simcol_with_a_gap: Path, tmp_path: Path) -> None:
    with pytest.warns(UserWarning, match="sequence S1: frame numbers not contiguous"):
        preprocess_dataset("simcol", preprocess_params("simcol", simcol_with_a_gap), tmp_path / "out")
    metas = shard_metas(tmp_path / "out")
    assert sorted(m["frame"] for m in metas if m["sequence"] == "S1") == [1, 2, 6]  # not 3 nor 5
    assert sorted(m["frame"] for m in metas if m["sequence"] == "S4") == [1, 2, 3, 4, 5, 6]
    for meta in metas:
        ids = meta["frame_ids"]
        assert (ids["prev"], ids["next"]) == (ids["cur"] - 1, ids["cur"] + 1)


def test_the_gt_check_measures_no_pair_across_the_gap(simcol_with_a_gap: Path) -> None:
    sequences, _ = read_sequences(simcol_with_a_gap)
    result = check_sequence(sequences["S1"], max_frames=100)
    # 7 frames give 12 neighbour pairs; the two across the gap (3 <-> 5) are not measured
    assert result["pairs"] == 10


def sequence_numbered(frame_ids: list[int]) -> Sequence:
    return Sequence("simcol", "S", "train", np.eye(3), (8, 8), frame_ids, None, None, None)


@pytest.mark.parametrize(
    ("frame_ids", "offset", "targets"),
    [
        ([0, 1, 2, 3, 5, 6, 7], 1, [1, 2, 6]),
        ([0, 1, 2, 3, 4, 6, 7, 8, 9, 10], 2, [2, 8]),
        ([0, 25, 50, 100, 125, 150], 1, [25, 125]),  # SceneNet-like numbering: the step is 25
        ([10, 12, 14, 16], 1, [12, 14]),
    ],
)
def test_targets_need_neighbours_exactly_offset_frame_steps_away(
    frame_ids: list[int], offset: int, targets: list[int]
) -> None:
    settings = EncodeSettings("simcol", 8, offset, (offset,), 0.001, depth_only=False, reader_params="{}")
    assert [s.frame for s in sequence_samples(sequence_numbered(frame_ids), settings)] == targets


def test_missing_frame_ids_follow_the_regular_step() -> None:
    assert missing_frame_ids([0, 1, 2, 3, 5, 6, 9]) == [4, 7, 8]
    assert missing_frame_ids([0, 25, 50, 100]) == [75]
    assert missing_frame_ids([7]) == []


# ---------------------------------------------------------------- synthetic sequences rendered at once
def test_a_sequence_rendered_twice_at_the_same_time_ends_up_whole(tmp_path: Path, monkeypatch) -> None:
    """A second render of the same sequence runs while the first is half written (two processes, one
    output): each has its own temporary folder, so neither destroys the other's frames."""
    clean_job = plan_jobs("simcol", tmp_path / "clean", 1, 3, 16, 0, "cpu", Params())[0]
    render_job(clean_job)
    clean = Path(clean_job.target)
    job = plan_jobs("simcol", tmp_path / "twice", 1, 3, 16, 0, "cpu", Params())[0]
    write_png, written = writers.write_png, []

    def write_png_then_interleave(path: Path, array: np.ndarray) -> None:
        write_png(path, array)
        written.append(path)
        if len(written) == 2:  # the first render has written frame 0: the second one runs to the end
            render_job(job)

    monkeypatch.setattr(writers, "write_png", write_png_then_interleave)
    render_job(job)
    target = Path(job.target)
    assert sorted(p.name for p in target.iterdir()) == sorted(p.name for p in clean.iterdir())
    for path in clean.iterdir():
        assert (target / path.name).read_bytes() == path.read_bytes(), path.name
    assert [p.name for p in target.parent.iterdir() if p.name.startswith(".")] == []
