"""Evaluation fed like training: loader processes decode the frames, the networks run on batches, a second thread
records them (on a GPU). The outputs must be those of evaluation in one thread of one process, to the bit, and a
damaged shard must still fail naming the file. Shards and model: the oracle shards of ``test_evaluate.py`` and an
untrained model at 64 px."""

from __future__ import annotations

import json
import re
import shutil
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch

from endoflow.config import EvalSetConfig, Params
from endoflow.data.loader import ordered_loader, triplet_dataset
from endoflow.data.sequences import frames_in_order, sequence_frames
from endoflow.data.shard_format import shard_entries
from endoflow.devices import unit_float_images
from endoflow.errors import DataFormatError
from endoflow.evaluation.evaluate import (EvaluationFeed, SequenceEvaluator, batches_within_sequences, belongs_to,
                                          eval_set_shards, evaluate_test_set, predict_then_record, score_sequences)
from endoflow.geometry.direct_alignment import tracker_settings
from endoflow.models.endoflow_model import load_trained_model
from tests.module_temp import ModuleTemp
from tests.test_evaluate import oracle_shards, shard_params, write_untrained_model  # noqa: F401 (a fixture)

TEST_SET = "simcol_12"  # two sequences of 7 frames in three shards: batches of 3 alternate between processes


def evaluate(params: Params, shards: Path, model: Path, out: Path, loader_workers: int, threads: int) -> dict:
    # the loader processes and the process reading them fit the CPUs a training worker reserves
    params = params.replace(train=params.train.replace(loader_workers=loader_workers), threads=threads,
                            ray=params.ray.replace(cpus_per_worker=float(loader_workers + 1)))
    urls = eval_set_shards(str(shards), params.eval.test_sets[TEST_SET])
    return evaluate_test_set(params, TEST_SET, urls, model, out / "metrics.json", out / "plots", out / "predictions")


def written_files(folder: Path) -> dict[str, bytes]:
    return {str(path.relative_to(folder)): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


@pytest.fixture(scope="module")
def untrained(oracle_shards: Path, module_tmp: ModuleTemp) -> tuple[Params, Path]:  # noqa: F811
    params = shard_params(oracle_shards)
    params.eval.batch_size = 3
    params.model = params.model.replace(latent_bank=False)
    model = module_tmp("model") / "endoflow.pt"
    write_untrained_model(model, params, None)
    return params, model


def test_loader_processes_write_what_one_process_writes_to_the_bit(
        oracle_shards: Path, untrained: tuple[Params, Path], tmp_path: Path) -> None:  # noqa: F811
    params, model = untrained
    fed = evaluate(params, oracle_shards, model, tmp_path / "fed", loader_workers=2, threads=3)
    alone = evaluate(params, oracle_shards, model, tmp_path / "alone", loader_workers=0, threads=1)
    assert fed["frames"] == alone["frames"] == 14 and fed["sequences"] == 2
    fed_files = written_files(tmp_path / "fed" / "predictions")
    alone_files = written_files(tmp_path / "alone" / "predictions")
    assert sorted(fed_files) == sorted(alone_files)
    assert {"per_frame.csv", "per_sequence.csv", "trajectory.csv"} <= set(fed_files)
    assert len([name for name in fed_files if name.endswith(".npy")]) == 14
    # the timing differs, every figure is the same
    json_files = {name for name in fed_files if name.endswith(".json")}
    assert {name for name in fed_files if fed_files[name] != alone_files[name]} <= json_files
    for name in json_files:
        fed_json, alone_json = json.loads(fed_files[name]), json.loads(alone_files[name])
        fed_json.pop("frames_per_second", None), alone_json.pop("frames_per_second", None)
        assert fed_json == alone_json, name
    assert (tmp_path / "fed" / "metrics.json").read_bytes() == (tmp_path / "alone" / "metrics.json").read_bytes()


def evaluator(params: Params, model_file: Path, out: Path, scoring: ThreadPoolExecutor | None) -> SequenceEvaluator:
    model, record = load_trained_model(model_file, torch.device("cpu"))
    return SequenceEvaluator(model, record.baselines, out, torch.device("cpu"), "float32", 2,
                             tracker_settings(params.refine), scoring)


def test_recording_beside_the_networks_gives_what_recording_after_them_gives(
        oracle_shards: Path, untrained: tuple[Params, Path], tmp_path: Path) -> None:  # noqa: F811
    """The GPU's way (a recording thread, scoring threads, the refined path tracked beside the networks), run here
    on the CPU, against one thread doing everything in turn."""
    params, model = untrained
    test_set = params.eval.test_sets[TEST_SET]
    urls = eval_set_shards(str(oracle_shards), test_set)
    keep = partial(belongs_to, test_set=test_set)
    with ThreadPoolExecutor(3) as scoring:
        beside = evaluator(params, model, tmp_path / "beside", scoring)
        feed = EvaluationFeed(urls, shard_entries(urls), keep, None, params.eval.batch_size, beside.baselines)
        predict_then_record(beside, ordered_loader(feed, 2), overlapped=True)
    after = evaluator(params, model, tmp_path / "after", None)
    for batch in batches_within_sequences(sequence_frames(urls, keep), params.eval.batch_size):
        after.process(batch)
    assert written_files(tmp_path / "beside") == written_files(tmp_path / "after")
    (summary, *tables, trajectories), expected = score_sequences(beside), score_sequences(after)
    assert summary == expected[0] and "refined" in summary["pose_simcol"]
    for table, expected_table in zip(tables, expected[1:3]):
        assert table.equals(expected_table)
    for name, trajectory in trajectories.items():
        assert all(np.array_equal(trajectory[key], expected[3][name][key]) for key in trajectory)
    assert [example["rgb"].tobytes() for example in beside.examples] == [
        example["rgb"].tobytes() for example in after.examples]


@pytest.mark.parametrize("loader_workers", [0, 2])
def test_a_damaged_shard_fails_the_evaluation_naming_the_file(
        oracle_shards: Path, untrained: tuple[Params, Path], tmp_path: Path, loader_workers: int) -> None:  # noqa: F811
    params, model = untrained
    shards = tmp_path / "shards"
    shutil.copytree(oracle_shards, shards)
    damaged = eval_set_shards(str(shards), params.eval.test_sets[TEST_SET])[1]
    data = bytearray(Path(damaged).read_bytes())
    data[len(data) // 2] ^= 0xFF
    Path(damaged).write_bytes(bytes(data))
    with pytest.raises(DataFormatError, match=re.escape(damaged)):
        evaluate(params, shards, model, tmp_path / "out", loader_workers=loader_workers, threads=2)


def test_frames_decoded_one_member_each_are_those_of_whole_decoded_samples(oracle_shards: Path) -> None:  # noqa: F811
    """The reader decodes a frame's one image (8-bit) and its depth; decoding every member of every sample (as the
    triplet reader does) gives the same frames."""
    urls = eval_set_shards(str(oracle_shards), EvalSetConfig(dataset="simcol"))
    lazily, wholly = list(sequence_frames(urls, max_frames=4)), list(frames_in_order(triplet_dataset(urls), 4))
    assert [(f.sequence, f.frame, f.after_gap) for f in lazily] == [(f.sequence, f.frame, f.after_gap) for f in wholly]
    for lazy, whole in zip(lazily, wholly):
        assert lazy.rgb.dtype == torch.uint8
        assert np.array_equal(unit_float_images(lazy.rgb).numpy(), whole.rgb.numpy())
        assert (lazy.depth_cm is None) == (whole.depth_cm is None)
        if lazy.depth_cm is not None:
            assert np.array_equal(lazy.depth_cm, whole.depth_cm)
        assert np.array_equal(lazy.pose, whole.pose) and np.array_equal(lazy.K, whole.K)
