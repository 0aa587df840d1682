"""The trivial baselines training stores in the model file, computed from the train shards."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from endoflow.config import Params
from endoflow.data.shards import preprocess_dataset
from endoflow.geometry.pose import relative_pose
from endoflow.training.ray_trainer import training_baselines
from tests.fixtures_native import write_simcol


def baseline_step(root: Path, out: Path, neighbour_offset: int, train_offsets: list[int] | None = None) -> np.ndarray:
    """The constant-velocity step of the train shards that ``neighbour_offset`` (or ``train_offsets``) makes from
    the SimCol ``root``."""
    params = Params()
    params.data.simcol.root = str(root)
    params.data.size = 32
    params.preprocess = params.preprocess.replace(out=str(out), engine="local", workers=1,
                                                  neighbour_offset=neighbour_offset, train_offsets=train_offsets)
    preprocess_dataset("simcol", params, out / "simcol")
    urls = sorted(str(path) for path in (out / "simcol").glob("train-*.tar"))
    return training_baselines(urls).mean_relative_pose


def test_the_constant_velocity_step_is_one_frame_whatever_the_neighbour_offset(tmp_path: Path) -> None:
    sequences = write_simcol(tmp_path / "simcol", frames=9, size=32)
    path = sequences["S1"].T_world_cam  # the one train sequence
    consecutive = baseline_step(tmp_path / "simcol", tmp_path / "offset1", 1)
    two_apart = baseline_step(tmp_path / "simcol", tmp_path / "offset2", 2)
    mixed = baseline_step(tmp_path / "simcol", tmp_path / "mixed", 1, train_offsets=[1, 2, 3])
    one_frame = relative_pose(path[4], path[5])
    # the fixture's path changes its step slowly: every estimate is the step of one frame, not of two or three
    assert np.abs(two_apart - consecutive).max() < 0.1 * np.abs(one_frame - np.eye(4)).max()
    assert np.abs(mixed - consecutive).max() < 0.1 * np.abs(one_frame - np.eye(4)).max()
    np.testing.assert_allclose(consecutive, one_frame, atol=0.1 * np.abs(one_frame - np.eye(4)).max())
