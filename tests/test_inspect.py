"""``endoflow data inspect`` and the reader registry: layout detection, the report, its text form."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from endoflow.cli import main
from endoflow.config import Params
from endoflow.data.endoslam import EndoSLAMReader
from endoflow.data.inspect import format_inspection, inspect_dataset
from endoflow.data.registry import detect_dataset, open_reader
from endoflow.data.scenenet import SceneNetReader
from endoflow.data.simcol import SimColReader
from endoflow.errors import DataFormatError
from tests.fixtures_native import write_endoslam_unitycam, write_scenenet, write_simcol
from tests.samples import SIMCOL_SAMPLE



# ----------------------------------------------------------------------------------- registry
@pytest.mark.parametrize(
    "write, name, reader",
    [(write_simcol, "simcol", SimColReader), (write_endoslam_unitycam, "endoslam", EndoSLAMReader),
     (write_scenenet, "scenenet", SceneNetReader)],
)
def test_layout_detection(tmp_path, write, name, reader):
    write(tmp_path)
    assert detect_dataset(tmp_path) == name
    assert isinstance(open_reader(tmp_path, None, Params()), reader)


def test_unknown_layout_names_the_root_and_the_expected_layouts(tmp_path):
    (tmp_path / "train").mkdir()  # a bare train/ is not SceneNet
    with pytest.raises(DataFormatError, match="no known dataset layout found; expected one of: simcol") as info:
        open_reader(tmp_path, None, Params())
    assert info.value.path == tmp_path


def test_ambiguous_layout_asks_for_the_dataset_name(tmp_path):
    write_simcol(tmp_path, frames=1, size=8)
    write_scenenet(tmp_path)
    with pytest.raises(DataFormatError, match="matches several datasets .simcol, scenenet."):
        open_reader(tmp_path, None, Params())
    assert isinstance(open_reader(tmp_path, "scenenet", Params()), SceneNetReader)


def test_unknown_dataset_name(tmp_path):
    with pytest.raises(DataFormatError, match="unknown dataset 'kitti'"):
        open_reader(tmp_path, "kitti", Params())


# ------------------------------------------------------------------------------------ inspect
def test_inspect_reports_what_the_reader_understood(tmp_path):
    truth = write_simcol(tmp_path, frames=4)
    report = inspect_dataset(tmp_path, None, Params())
    assert report["dataset"] == "simcol" and report["frames_per_split"] == {"train": 4, "val": 4, "test": 4}
    entry = {e["name"]: e for e in report["sequences"]}["S4"]
    expected = truth["S4"]
    assert (entry["split"], entry["group"], entry["frames"]) == ("val", "SyntheticColon_I", 4)
    assert entry["image_size"] == [32, 32]
    np.testing.assert_allclose(entry["K"], expected.K)
    sampled = np.stack([expected.depth_cm[i] for i in entry["depth_cm"]["sampled_frames"]])
    assert entry["depth_cm"]["sampled_frames"] == [0, 2, 3]
    assert entry["depth_cm"]["min"] == pytest.approx(sampled.min(), rel=1e-6)
    assert entry["depth_cm"]["max"] == pytest.approx(sampled.max(), rel=1e-6)
    assert entry["poses"]["known"] == 4
    np.testing.assert_allclose(entry["poses"]["first"]["T_world_cam"], expected.T_world_cam[0], atol=1e-12)
    np.testing.assert_allclose(entry["poses"]["last"]["T_world_cam"], expected.T_world_cam[3], atol=1e-12)
    json.dumps(report)  # JSON-ready as it is

    text = format_inspection(report)
    assert "S4  [split val, group SyntheticColon_I]  4 frames (0..3), 32x32" in text
    assert f"{expected.K[0, 0]:12.6f}" in text and f"{expected.T_world_cam[3, 2, 3]:12.6f}" in text


def test_inspect_shows_alignment_problems_and_unknown_poses(tmp_path):
    write_endoslam_unitycam(tmp_path, frames=8, matched=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # inspect shows problems in the report, not as warnings
        report = inspect_dataset(tmp_path, "endoslam", Params())
    (entry,) = report["sequences"]
    assert entry["poses"]["known"] == 5
    assert (entry["poses"]["first"]["frame"], entry["poses"]["last"]["frame"]) == (0, 4)
    assert any("aligned by time" in p for p in entry["problems"])
    assert "aligned by time" in format_inspection(report)


def test_inspect_reports_an_undecodable_frame_as_a_problem(tmp_path):
    write_scenenet(tmp_path, frame_ids=(0, 25, 50))
    depth = tmp_path / "train" / "0" / "7" / "depth" / "50.png"
    depth.write_bytes(b"broken")
    report = inspect_dataset(tmp_path, None, Params())
    (entry,) = report["sequences"]
    assert entry["poses"] is None
    assert entry["depth_cm"]["sampled_frames"] == [0, 25, 50]
    assert entry["depth_cm"]["min"] == pytest.approx(150, abs=0.05)
    assert any(p.startswith("frame 50:") and str(depth) in p and "unreadable image" in p for p in entry["problems"])
    assert "poses: none" in format_inspection(report)


@pytest.mark.skipif(
    not (SIMCOL_SAMPLE / "SyntheticColon_I").is_dir(), reason=f"real SimCol3D sample not found at {SIMCOL_SAMPLE}"
)
def test_cli_inspect_shows_literal_K_and_converted_poses_of_the_real_sample(tmp_path, capsys):
    assert main(["--params", str(tmp_path / "none.yaml"), "data", "inspect", str(SIMCOL_SAMPLE)]) == 0
    text = capsys.readouterr().out
    assert "S1  [split train, group SyntheticColon_I]  10 frames (0..9), 475x475" in text
    assert "227.604160     0.000000   227.604160" in text and "0.000000   237.500000   237.500000" in text
    assert "-0.080967    -0.002823     0.996713   -30.504590" in text  # frame 0, official conversion
    assert "-0.952287    -0.293113    -0.085057    -3.084473" in text  # frame 9
    assert "problems: none" in text


def test_cli_inspect_json_and_error_exit(tmp_path, capsys):
    write_scenenet(tmp_path / "scenenet")
    assert main(["--params", str(tmp_path / "none.yaml"), "data", "inspect", str(tmp_path / "scenenet"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["dataset"] == "scenenet"
    assert main(["--params", str(tmp_path / "none.yaml"), "data", "inspect", str(tmp_path / "missing")]) == 2
    assert "dataset root folder not found" in capsys.readouterr().err


@pytest.mark.skipif(not SIMCOL_SAMPLE.is_dir(), reason=f"real SimCol3D sample not found at {SIMCOL_SAMPLE}")
def test_inspect_gives_the_real_colonoscope_motion_per_frame():
    """The figures the built-in renderer's camera paths are calibrated on (docs/synthetic_data.md)."""
    (sequence,) = inspect_dataset(SIMCOL_SAMPLE, "simcol", Params())["sequences"]
    motion = sequence["poses"]["motion"]
    assert motion["step_mm"] == pytest.approx(1.351, abs=1e-3)
    assert motion["rotation_deg"] == pytest.approx(0.1155, abs=1e-3)
    assert motion["step_change_mm"] == pytest.approx(0.0091, abs=1e-4)
    assert motion["rotation_change_deg"] == pytest.approx(0.0166, abs=1e-3)
    assert motion["forward_share"] == 1.0
    assert "motion per frame (medians): step 1.351 mm, rotation 0.116 deg" in format_inspection(
        inspect_dataset(SIMCOL_SAMPLE, "simcol", Params()))
