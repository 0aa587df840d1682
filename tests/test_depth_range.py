"""The share of a depth map at the ends of the model's range, which tells a collapsed depth network from a
working one without ground truth: hand-computed pixels, the network's own saturated output, and the warnings
training and `reconstruct` give."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from endoflow.config import ModelConfig
from endoflow.models.depth_range import COLLAPSED_SHARE, at_depth_range_ends, collapsed_depth_warning
from endoflow.training.ray_trainer import depth_collapse_warning, depth_collapsed_epochs, epoch_ranges
from tests.test_evaluate import oracle_shards  # noqa: F401 (a fixture)

CFG = ModelConfig(min_depth=0.1, max_depth=20.0)
# within 1 % of either end, or not
DEPTHS = [0.1, 0.1005, 0.102, 2.4, 19.7, 19.9, 20.0]
AT_ENDS = [True, True, False, False, False, True, True]


def test_pixels_within_a_percent_of_either_end_of_the_range_count_as_tensors_and_as_arrays():
    assert at_depth_range_ends(torch.tensor(DEPTHS), CFG).tolist() == AT_ENDS
    assert at_depth_range_ends(np.array(DEPTHS, np.float32), CFG).tolist() == AT_ENDS


def test_a_saturated_disparity_sigmoid_gives_depth_at_the_ends_and_a_mid_range_one_does_not():
    from endoflow.models.endoflow_model import EndoflowModel

    model = EndoflowModel.__new__(EndoflowModel)  # disp_to_depth needs only the config
    model.cfg = CFG
    disparity = torch.sigmoid(torch.tensor([-40.0, 40.0, 0.0, -3.0]))
    assert at_depth_range_ends(model.disp_to_depth(disparity), CFG).tolist() == [True, True, False, False]


def test_the_warning_starts_at_half_the_pixels_and_names_where_and_the_range():
    assert collapsed_depth_warning(COLLAPSED_SHARE - 1e-6, CFG, "of these frames") is None
    warning = collapsed_depth_warning(0.93, CFG, "of these frames")
    assert warning.startswith("93% of the depth of these frames sits at an end of its range (0.1-20 cm")
    assert "model.max_depth" in warning and "loss.automask" in warning


def test_training_names_the_epochs_whose_validation_depth_collapsed_and_whether_the_model_file_is_one():
    history = [{"epoch": 1, "val_depth_at_range_ends": 0.08}, *({"epoch": e, "val_depth_at_range_ends": 0.99}
                                                               for e in range(2, 11))]
    assert depth_collapsed_epochs(history) == list(range(2, 11))
    assert depth_collapsed_epochs([{"epoch": 1, "val_photometric": 0.1}]) == []  # an older history: no key
    before = depth_collapse_warning({"depth_collapsed_epochs": list(range(2, 11)), "best_epoch": 1})
    assert before.startswith("after epochs 2-10 25% of the validation depth or more sat at an end of its range")
    assert "the model file is epoch 1's, whose validation depth had not" in before
    one = depth_collapse_warning({"depth_collapsed_epochs": [3], "best_epoch": 3})
    assert one.startswith("after epoch 3 ") and "the model file's depth is one of them" in one
    assert depth_collapse_warning({"depth_collapsed_epochs": [], "best_epoch": 3}) is None
    assert depth_collapse_warning({"best_epoch": 3}) is None  # a summary from before the key


def test_an_epoch_at_exactly_the_collapsed_share_counts_and_one_just_below_does_not():
    history = [{"epoch": 1, "val_depth_at_range_ends": COLLAPSED_SHARE},
               {"epoch": 2, "val_depth_at_range_ends": np.nextafter(COLLAPSED_SHARE, 0.0)}]
    assert depth_collapsed_epochs(history) == [1]
    assert collapsed_depth_warning(COLLAPSED_SHARE, CFG, "of these frames").startswith("25% of the depth")


def test_the_train_stage_prints_its_summary_and_puts_a_collapse_warning_on_stderr(
        tmp_path, monkeypatch, capsys):
    from stages import train as stage

    summary = {"epochs": 10, "global_steps": 500, "best_epoch": 1, "final_train_loss": 0.1234,
               "mlflow_run_id": "abc", "depth_collapsed_epochs": list(range(2, 11))}
    monkeypatch.setattr(stage, "train", lambda params: summary)
    monkeypatch.setattr("sys.argv", ["stage", "--params", str(tmp_path / "params.yaml")])
    (tmp_path / "params.yaml").write_text("{}\n")
    stage.main()
    printed = capsys.readouterr()
    assert printed.out.startswith("[train] done: 10 epochs, 500 steps; best epoch 1") and "warning" not in printed.out
    assert printed.err == f"[train] warning: {depth_collapse_warning(summary)}\n"
    monkeypatch.setattr(stage, "train", lambda params: {**summary, "depth_collapsed_epochs": []})
    stage.main()
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("epochs, text", [([1], "1"), ([2, 3, 4, 7], "2-4, 7"), ([5, 1, 2], "1-2, 5")])
def test_epochs_are_listed_as_runs(epochs, text):
    assert epoch_ranges(epochs) == text


def test_validation_reports_the_share_of_pixels_at_the_range_ends_near_0_for_a_working_and_1_for_a_collapsed_network(
        oracle_shards):
    from endoflow.data.loader import list_shards
    from endoflow.data.shard_format import shard_entries
    from endoflow.models.endoflow_model import build_model
    from endoflow.training.loop import EpochContext, validate
    from endoflow.training.worker_config import WorkerConfig
    from tests.small_model import small_model_params

    params = small_model_params(64)
    params.train = params.train.replace(batch_size=2, val_batches=1, loader_workers=0)
    val = tuple(list_shards(str(oracle_shards / "simcol"), "val"))
    config = WorkerConfig(params, ((),), val, None, "", "", None, batch_shares=(params.train.batch_size,))
    torch.manual_seed(0)
    model = build_model(params, latent_bank_path=None)

    def share() -> float:
        context = EpochContext(config, model, model, None, shard_entries(val), 0, 1, torch.device("cpu"), None)
        return validate(context)["val_depth_at_range_ends"]

    assert share() == 0.0  # untrained: about 0.2 cm everywhere, neither end
    head = model.depth_net.decoder.dispconvs[0]
    with torch.no_grad():
        head.weight.zero_()
        head.bias.fill_(-40.0)  # sigmoid(-40): every pixel at max_depth
    assert share() == 1.0
