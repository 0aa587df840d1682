"""What `dvc metrics show` and `dvc exp show` read: the metrics files of every stage, as their writers make them
for params.yaml. No key is in two files (an evaluation's test set and a reconstructed sequence may share a name)
and every figure's name says its unit, or it is a known unitless figure."""

from __future__ import annotations

import pytest

from endoflow.config import load_params
from endoflow.evaluation import results
from endoflow.reconstruction import measure
from endoflow.training import pretrain, ray_trainer
from tests.project_clone import PROJECT

UNIT_SUFFIXES = ("_cm", "_deg", "_pct")
# figures without a unit: ratios (Abs Rel; SWD is a distance between normalised descriptors, times 1e3) and counts
UNITLESS = {"abs_rel", "val_abs_rel", "swd_final", "swd_ratio", "best_epoch"}


def evaluation_result() -> dict:
    """An evaluation result with every protocol's model figures, as ``evaluate_test_set`` returns it."""
    return {"depth_paper": {"model": {"abs_rel": 0.2, "rmse": 0.5}, "constant_depth": {"abs_rel": 0.4}},
            "pose_simcol": {"model": {"ate": 1.0, "ate_local": 0.9, "rte": 0.05, "rot": 0.7}}}


def measurement_result() -> dict:
    """A reconstruction's measurement, as ``measure_reconstruction`` returns it (without per-frame errors)."""
    path = {"ate_rmse": 0.8, "ate_mean": 0.7, "ate_median": 0.6, "scale": 1.1, "rpe_trans": 0.1, "rpe_rot": 0.4}
    surface = {"accuracy_mean": 0.3, "accuracy_median": 0.2, "completeness_mean": 0.4, "completeness_median": 0.3,
               "completeness_ratio": 0.75}
    return {"path": {"model": path, "constant_velocity": path}, "surface": {"model": surface, "trivial": surface}}


def metrics_files() -> dict[str, dict]:
    """``{metrics file: content}`` of every stage for params.yaml."""
    params = load_params(PROJECT / "params.yaml")
    training = {"epochs": 10, "global_steps": 100, "best_epoch": 9, "val_abs_rel": 0.2, "val_rmse": 0.4,
                "val_images": 12, "final_train_loss": 0.1, "mlflow_run_id": "0" * 32, "fingerprint": "0" * 16}
    bank = {"swd_untrained": 250.0, "swd_final": 50.0, "swd_real_reference": 20.0, "swd_ratio": 0.2,
            "swd_final_levels": [40.0, 60.0], "seconds": 12.0}
    files = {params.train.metrics: ray_trainer.train_dvc_metrics(training),
             params.latent_bank.metrics: pretrain.dvc_metrics(bank)}
    files |= {f"{params.eval.metrics}/{name}.json": results.dvc_metrics(name, evaluation_result())
              for name in params.eval.test_sets}
    files |= {f"{params.reconstruct.metrics}/{name}.json": measure.dvc_metrics(name, measurement_result())
              for name in params.reconstruct.sequences}
    return files


def leaves(tree: dict, prefix: str = "") -> dict[str, object]:
    flat = {}
    for key, value in tree.items():
        flat |= leaves(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value}
    return flat


def test_no_top_level_key_is_in_two_metrics_files():
    owners: dict[str, list[str]] = {}
    for path, content in metrics_files().items():
        for key in content:
            owners.setdefault(key, []).append(path)
    shared = {key: paths for key, paths in owners.items() if len(paths) > 1}
    assert not shared, shared


@pytest.mark.parametrize("path", sorted(metrics_files()))
def test_every_figure_names_its_unit_or_is_a_known_unitless_figure(path: str):
    figures = leaves(metrics_files()[path])
    assert figures, path
    for name, value in figures.items():
        assert isinstance(value, (int, float)) and not isinstance(value, bool), (path, name, value)
        leaf = name.rsplit(".", 1)[-1]
        assert leaf.endswith(UNIT_SUFFIXES) or leaf in UNITLESS, f"{path}: {name} names no unit"


def test_the_headlines_carry_each_figure_in_its_unit():
    evaluation = results.dvc_metrics("simcol_3", evaluation_result())
    assert evaluation == {"test_simcol_3": {"abs_rel": 0.2, "rte_cm": 0.05, "rot_deg": 0.7}}
    reconstruction = measure.dvc_metrics("simcol_S5", measurement_result())
    assert reconstruction == {"reconstruct_simcol_S5": {"ate_cm": 0.8, "accuracy_cm": 0.2,
                                                        "completeness_2vox_pct": pytest.approx(75.0)}}
