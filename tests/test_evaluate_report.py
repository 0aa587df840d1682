"""`endoflow report`: Markdown tables from the full evaluations of the workspace and of DVC's experiments."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from endoflow.cli import main
from endoflow.evaluation.summary import format_evaluation, markdown_table
from endoflow.report import (
    RunResults,
    experiment_results,
    format_report,
    running_in_workspace,
    runs_by_configuration,
    workspace_results,
)


def evaluation(abs_rel: float, rte: float) -> dict:
    return {
        "test_set": "simcol_12",
        "depth_paper": {"model": {"abs_rel": abs_rel, "sq_rel": 0.1, "rmse": 1.0, "rmse_log": 0.2, "l1": 0.5,
                                  "a1": 0.8, "a2": 0.9, "a3": 0.95, "ratio": 1.25, "near_ratio": 0.9,
                                  "far_ratio": 1.3},
                        "constant_depth": {"abs_rel": 0.5, "a1": 0.3}},
        "depth_simcol": {"model": {"l1": 0.4, "rel": 9.0, "rmse": 0.7}},
        "pose_simcol": {"model": {"ate": 2.0, "ate_local": 0.6, "rte": rte, "rot": 1.5},
                        "constant_velocity": {"ate": 4.0, "ate_local": 0.6, "rte": 0.9}},
    }


def table_rows(text: str) -> list[list[str]]:
    """The cells of every table row in ``text``, stripped."""
    return [[cell.strip() for cell in line.strip().strip("|").split("|")]
            for line in text.splitlines() if line.startswith("|")]


def exp_show(experiments: dict[str, tuple[bool, bool]], running: str | None = None) -> list[dict]:
    """The shape `dvc exp show --json` prints: baseline commits, each with ranges of experiment revisions."""
    def state(rev: str, name: str | None, bank: bool, vae: bool) -> dict:
        params = {"model": {"latent_bank": bank, "pose_vae": vae}, "eval": {"test_sets": {"simcol_12": {}}}}
        return {"rev": rev, "name": name, "error": None, "experiments": None,
                "data": {"rev": rev, "params": {"params.yaml": {"data": params}}, "metrics": {}}}

    head = state("abc1234def", "main", True, True)
    head["experiments"] = [{"name": name, "executor": None, "revs": [state(f"{i:07d}", name, *flags)]}
                           for i, (name, flags) in enumerate(experiments.items())]
    if running:
        head["experiments"].append({"name": running, "executor": {"state": "running", "name": "workspace"},
                                    "revs": [state("9999999", running, False, False)]})
    return [state("workspace", None, True, True), head]


def reader(abs_rels: dict[str, float]):
    """``read(rev, path)`` over evaluation files that exist at some revisions only."""
    def read(rev: str, path: str) -> str | None:
        assert path == "predictions/simcol_12/evaluation.json"
        return json.dumps(evaluation(abs_rels[rev], 0.3)) if rev in abs_rels else None
    return read


def test_experiments_become_labelled_runs_read_at_their_revisions():
    states = exp_show({"no-bank": (False, True), "no-vae": (True, False)}, running="busy")
    runs = experiment_results(states, ".", "predictions", read=reader({"0000000": 0.2, "0000001": 0.15,
                                                                        "9999999": 0.5}))
    # the baseline commit has no evaluation; the running experiment is not a result yet
    assert [r.label for r in runs] == ["no-bank (bank off, VAE on)", "no-vae (bank on, VAE off)"]
    assert runs[0].test_sets["simcol_12"]["depth_paper"]["model"]["abs_rel"] == 0.2
    assert running_in_workspace(states) == "busy"
    assert running_in_workspace(exp_show({"no-bank": (False, True)})) is None


def write_evaluation(predictions: Path, abs_rel: float, rte: float) -> None:
    (predictions / "simcol_12").mkdir(parents=True)
    (predictions / "simcol_12" / "evaluation.json").write_text(json.dumps(evaluation(abs_rel, rte)))


def test_report_has_a_table_per_protocol_with_baselines_and_an_ablation_summary(tmp_path: Path):
    write_evaluation(tmp_path, 0.1234, 0.25)
    runs = [workspace_results(tmp_path, {"model": {"latent_bank": True, "pose_vae": True}}),
            *experiment_results(exp_show({"no-bank": (False, True)}), ".", "predictions",
                                read=reader({"0000000": 0.2}))]
    report = format_report(runs)
    assert "## simcol_12" in report
    assert "### Depth, paper protocol" in report and "### Depth, SimCol3D challenge protocol" in report
    rows = table_rows(report)
    assert ["workspace (bank on, VAE on)", "0.1234", "0.1000", "1.0000", "0.2000", "0.5000", "0.8000", "0.9000",
            "0.9500", "1.2500", "0.9000", "1.3000"] in rows
    assert ["baseline: constant depth", "0.5000", "–", "–", "–", "–", "0.3000", "–", "–", "–", "–", "–"] in rows
    assert ["baseline: constant velocity", "4.0000", "0.6000", "0.9000", "–"] in rows
    assert ["no-bank (bank off, VAE on)", "0.2000", "0.3000"] in table_rows(report.split("## Ablation summary")[1])
    assert "EndoSLAM protocol" not in report  # absent protocols get no empty table


def test_the_workspace_row_says_when_an_experiment_is_running_in_it(tmp_path: Path):
    write_evaluation(tmp_path, 0.1234, 0.25)
    run = workspace_results(tmp_path, {"model": {"latent_bank": False, "pose_vae": True}}, running="busy")
    assert run.label == "workspace: busy running, partial (bank off, VAE on)"


def test_markdown_tables_pad_their_columns_to_one_width():
    table = markdown_table(["run", "Abs Rel"], [["a long run name", "0.1"], ["b", "–"]])
    assert table.splitlines() == ["| run             | Abs Rel |",
                                  "| --------------- | ------- |",
                                  "| a long run name | 0.1     |",
                                  "| b               | –       |"]


def test_evaluation_summary_shows_the_model_beside_its_baselines_per_protocol():
    result = {**evaluation(0.1234, 0.25), "dataset": "simcol", "sequences": 3, "frames": 120, "depth_frames": 114,
              "frames_per_second": 41.25, "mlflow_run_id": "abc"}
    summary = format_evaluation(result)
    assert summary.startswith("Test set simcol_12 (simcol): 3 sequences, 120 frames, 114 frames with GT depth, "
                              "41.2 frames/s\n")
    sections = {block.splitlines()[0]: table_rows(block) for block in summary.split("\n\n")[1:]}
    assert list(sections) == ["Depth, paper protocol (per-image median scaling, capped at 20 cm)",
                              "Depth, SimCol3D challenge protocol (one scale per sequence)",
                              "Pose, SimCol3D challenge protocol (medians)"]  # no EndoSLAM metrics in the result
    paper = sections["Depth, paper protocol (per-image median scaling, capped at 20 cm)"]
    assert paper[0] == ["method", "Abs Rel", "Sq Rel", "RMSE", "RMSE log", "L1", "δ<1.25", "δ<1.25²", "δ<1.25³",
                        "Scale", "near GT/pred", "far GT/pred"]
    assert [row[:2] for row in paper[2:]] == [["model", "0.1234"], ["baseline: constant depth", "0.5000"]]
    pose = sections["Pose, SimCol3D challenge protocol (medians)"]
    assert pose[0] == ["method", "ATE (cm)", "ATE local (cm)", "RTE (cm)", "ROT (°)"]
    assert pose[2:] == [["model", "2.0000", "0.6000", "0.2500", "1.5000"],
                        ["baseline: constant velocity", "4.0000", "0.6000", "0.9000", "–"]]


def test_evaluation_summary_without_metrics_says_so():
    summary = format_evaluation({"test_set": "endoslam_colon", "dataset": "endoslam", "sequences": 1, "frames": 5,
                                 "depth_frames": 0})
    assert "No depth or pose metrics" in summary and "|" not in summary


def test_cli_report_on_a_workspace_without_metrics(tmp_path: Path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["report", "--no-experiments"]) == 0
    assert "No evaluation metrics found" in capsys.readouterr().out


def seeded_run(name: str, bank: bool, vae: bool, seed: int, abs_rel: float, rte: float) -> RunResults:
    return RunResults(name, {"seed": seed, "model": {"latent_bank": bank, "pose_vae": vae}},
                      {"simcol_12": evaluation(abs_rel, rte)})


def test_seed_statistics_give_mean_and_sd_per_configuration_and_mark_differences_beyond_the_spread():
    runs = [seeded_run("workspace", True, True, 0, 0.10, 0.50),
            seeded_run("full-s0", True, True, 0, 0.10, 0.50),  # the workspace's own experiment: counted once
            seeded_run("full-s1", True, True, 1, 0.12, 0.70),
            seeded_run("full-s2", True, True, 2, 0.14, 0.60),
            seeded_run("nobank-s0", False, True, 0, 0.20, 0.55),
            seeded_run("nobank-s1", False, True, 1, 0.22, 0.65),
            seeded_run("nobank-s2", False, True, 2, 0.24, 0.75)]
    text = format_report(runs)
    section = text[text.index("### simcol_12"):text.index("### Pose against constant velocity")]
    rows = table_rows(section)
    assert rows[0] == ["configuration", "seeds", "Abs Rel", "RTE (cm)", "ROT (°)", "ATE (cm)", "ATE local (cm)",
                       "far GT/pred (1)"]
    # full: Abs Rel 0.10, 0.12, 0.14 -> 0.12 ± 0.02; RTE 0.5, 0.7, 0.6 -> 0.6 ± 0.1
    assert rows[2] == ["full", "3", "0.1200 ± 0.0200", "0.6000 ± 0.1000", "1.5000 ± 0.0000", "2.0000 ± 0.0000",
                       "0.6000 ± 0.0000", "1.3000 ± 0.0000"]
    assert rows[3] == ["no-bank", "3", "0.2200 ± 0.0200", "0.6500 ± 0.1000", "1.5000 ± 0.0000", "2.0000 ± 0.0000",
                       "0.6000 ± 0.0000", "1.3000 ± 0.0000"]
    assert rows[4] == ["trivial baseline", "–", "0.5000", "0.9000", "–", "4.0000", "0.6000", "–"]
    # Abs Rel +0.10 > 0.02 + 0.02: beyond the spread; RTE +0.05 < 0.1 + 0.1: within it
    assert rows[5] == ["no-bank - full", "3", "+0.1000 *", "+0.0500", "+0.0000", "+0.0000", "+0.0000", "+0.0000"]


def test_pose_is_compared_with_constant_velocity_beyond_the_seed_spread():
    runs = [seeded_run("full-s0", True, True, 0, 0.10, 0.50), seeded_run("full-s1", True, True, 1, 0.12, 0.70),
            seeded_run("full-s2", True, True, 2, 0.14, 0.60),
            seeded_run("nobank-s0", False, True, 0, 0.20, 0.70), seeded_run("nobank-s1", False, True, 1, 0.22, 1.00)]
    text = format_report(runs)
    rows = table_rows(text[text.index("### Pose against constant velocity"):])
    assert rows[0] == ["configuration", "test set", "seeds", "RTE (cm)", "ROT (°)", "ATE (cm)", "ATE local (cm)"]
    # constant velocity: RTE 0.9, ATE 4.0, ATE local 0.6, no ROT. full: RTE 0.6 ± 0.1, 0.7 < 0.9, better beyond
    # its spread; ATE 2.0 ± 0 < 4.0, too; ATE local equal. no-bank: RTE 0.85 ± 0.21, below 0.9 but within its spread
    assert rows[2] == ["full", "simcol_12", "3", "-33.3 % *", "–", "-50.0 % *", "+0.0 %"]
    assert rows[3] == ["no-bank", "simcol_12", "2", "-5.6 %", "–", "-50.0 % *", "+0.0 %"]


def test_a_configuration_with_one_seed_has_no_spread_to_exceed():
    runs = [seeded_run("full-s0", True, True, 0, 0.10, 0.5), seeded_run("full-s1", True, True, 1, 0.12, 0.6),
            seeded_run("neither-s0", False, False, 0, 0.30, 0.5)]
    text = format_report(runs)
    rows = table_rows(text[text.index("### simcol_12"):text.index("### Pose against constant velocity")])
    assert rows[-1][:4] == ["neither - full", "1", "+0.1900", "-0.0500"]  # Abs Rel far off, yet unmarked
    pose = table_rows(text[text.index("### Pose against constant velocity"):])
    assert pose[-1][:4] == ["neither", "simcol_12", "1", "-44.4 %"]  # well below constant velocity, yet unmarked


def test_one_seed_per_configuration_gives_no_seed_section():
    runs = [seeded_run("full", True, True, 0, 0.1, 0.5), seeded_run("neither", False, False, 0, 0.2, 0.6)]
    assert "Seed statistics" not in format_report(runs)


def test_the_sweep_queues_every_configuration_with_every_seed_naming_each_switch():
    from endoflow.sweep import sweep_commands

    commands = sweep_commands([0, 1, 2])
    assert len(commands) == 12
    # the studies' settings too, at their defaults: the ablation does not inherit the workspace's
    defaults = ["-S", "model.pose_sample=true", "-S", "loss.kl_weight=1e-05", "-S", "preprocess.train_offsets=null",
                "-S", "loss.geometry_weight=0.0", "-S", "train.time_reversal=0.0", "-S", "loss.automask=true",
                "-S", "loss.automask_pose=true", "-S", "loss.automask_depth=true"]
    assert commands[0] == ["exp", "run", "--queue", "-n", "full-seed0", "-S", "model.latent_bank=true",
                           "-S", "model.pose_vae=true", *defaults, "-S", "seed=0", "evaluate"]
    assert commands[-1] == ["exp", "run", "--queue", "-n", "neither-seed2", "-S", "model.latent_bank=false",
                            "-S", "model.pose_vae=false", *defaults, "-S", "seed=2", "evaluate"]
    assert len({tuple(c) for c in commands}) == 12


def test_the_sweep_outside_a_dvc_project_fails_naming_the_command_and_the_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "params.yaml").write_text("")  # valid params (the defaults), so the sweep gets as far as DVC
    assert main(["sweep", "--seeds", "0", "--no-start"]) == 1
    error = capsys.readouterr().err
    assert "endoflow sweep: error: `dvc exp run --queue -n full-seed0" in error and str(tmp_path) in error


def test_the_vae_study_queues_the_full_model_without_sampling_and_with_beta_over_decades():
    from endoflow.sweep import sweep_commands

    commands = sweep_commands([0, 1], study="vae")
    assert len(commands) == 8
    assert commands[0] == ["exp", "run", "--queue", "-n", "vae-mean-warp-seed0", "-S", "model.latent_bank=true",
                           "-S", "model.pose_vae=true", "-S", "model.pose_sample=false",
                           "-S", "loss.kl_weight=1e-05", "-S", "preprocess.train_offsets=null",
                           "-S", "loss.geometry_weight=0.0", "-S", "train.time_reversal=0.0",
                           "-S", "loss.automask=true", "-S", "loss.automask_pose=true", "-S", "loss.automask_depth=true", "-S", "seed=0", "evaluate"]
    betas = [next(word for word in command if word.startswith("loss.kl_weight=")) for command in commands[:4]]
    assert betas == ["loss.kl_weight=1e-05", "loss.kl_weight=0.0", "loss.kl_weight=0.0001", "loss.kl_weight=0.001"]
    with pytest.raises(ValueError, match="study"):
        sweep_commands([0], study="vea")


def test_the_motion_study_queues_the_full_model_with_mixed_offsets_the_depth_consistency_and_both():
    from endoflow.sweep import sweep_commands

    commands = sweep_commands([0], study="motion")
    changed = [[word for word in command if word.startswith(("preprocess.train_offsets", "loss.geometry_weight",
                                                             "train.time_reversal"))]
               for command in commands]
    assert changed == [["preprocess.train_offsets=null", "loss.geometry_weight=0.0", "train.time_reversal=0.0"],
                       ["preprocess.train_offsets=[1,2,3]", "loss.geometry_weight=0.0", "train.time_reversal=0.0"],
                       ["preprocess.train_offsets=null", "loss.geometry_weight=0.5", "train.time_reversal=0.0"],
                       ["preprocess.train_offsets=[1,2,3]", "loss.geometry_weight=0.5", "train.time_reversal=0.0"],
                       ["preprocess.train_offsets=null", "loss.geometry_weight=0.0", "train.time_reversal=0.25"]]


def test_the_mask_study_queues_the_full_model_without_auto_masking_and_with_it_for_the_pose_alone():
    from endoflow.sweep import sweep_commands

    commands = sweep_commands([0], study="mask")
    names = [command[command.index("-n") + 1] for command in commands]
    changed = [[word for word in command if word.startswith("loss.automask")] for command in commands]
    assert names == ["mask-base-seed0", "mask-off-seed0", "mask-pose-only-seed0"]
    assert changed == [["loss.automask=true", "loss.automask_pose=true", "loss.automask_depth=true"],
                       ["loss.automask=false", "loss.automask_pose=true", "loss.automask_depth=true"],
                       ["loss.automask=true", "loss.automask_pose=true", "loss.automask_depth=false"]]


def test_mask_study_runs_are_named_by_their_mask():
    def run(**loss) -> RunResults:
        return RunResults("r", {"model": {"latent_bank": True, "pose_vae": True}, "loss": loss})

    assert run(automask=True, automask_depth=True).configuration == "full"
    assert run(automask=False).configuration == "full, no automask"
    assert run(automask_depth=False).configuration == "full, depth unmasked"
    assert run(automask_pose=False).configuration == "full, pose unmasked"
    # without auto-masking, neither split does anything: the run is the unmasked one
    assert run(automask=False, automask_depth=False).configuration == "full, no automask"


@pytest.mark.parametrize("study", ["ablation", "vae", "motion", "mask"])
def test_the_sweeps_settings_as_dvc_writes_them_load_as_the_studys_values(tmp_path: Path, study: str):
    """`-S` as DVC applies it to the queued copy's params.yaml (Hydra's override grammar, written back by ruamel),
    then read by endoflow's config."""
    import yaml
    from dvc.utils.hydra import apply_overrides

    from endoflow.config import Params, load_params, params_to_dict
    from endoflow.sweep import study_configurations, sweep_commands

    for command, (_, settings) in zip(sweep_commands([3], study), study_configurations(study)):
        path = tmp_path / "params.yaml"
        path.write_text(yaml.safe_dump(params_to_dict(Params())))
        apply_overrides(path, [command[i + 1] for i, word in enumerate(command) if word == "-S"])
        params = load_params(path)
        for key, value in settings.items():
            section, name = key.split(".")
            assert getattr(getattr(params, section), name) == value, key
        assert params.seed == 3


def study_run(name: str, seed: int, abs_rel: float, *, sample: bool = True, beta: float = 1e-5,
              vae: bool = True) -> RunResults:
    params = {"seed": seed, "model": {"latent_bank": True, "pose_vae": vae, "pose_sample": sample},
              "loss": {"kl_weight": beta}}
    return RunResults(name, params, {"simcol_12": evaluation(abs_rel, 0.5)})


def test_vae_study_runs_are_their_own_configurations_named_by_the_setting():
    assert study_run("a", 0, 0.1).configuration == "full"
    assert study_run("a", 0, 0.1, sample=False).configuration == "full, mean warp"
    assert study_run("a", 0, 0.1, beta=1e-3).configuration == "full, β=0.001"
    assert study_run("a", 0, 0.1, beta=0.0).configuration == "full, β=0"
    # without the VAE there is nothing to sample and no KL: the settings do not split no-vae
    assert study_run("a", 0, 0.1, vae=False, sample=False, beta=1e-3).configuration == "no-vae"
    # DVC writes beta as 1e-05, which YAML 1.1 reads back as a string
    assert RunResults("dvc", {"model": {"latent_bank": True, "pose_vae": True},
                              "loss": {"kl_weight": "1e-05"}}).configuration == "full"
    # runs from before the setting existed are the default
    assert RunResults("old", {"model": {"latent_bank": True, "pose_vae": True}}).configuration == "full"


def test_motion_study_runs_are_named_by_their_offsets_and_consistency_weight_with_or_without_the_vae():
    def run(vae: bool, **changes) -> RunResults:
        return RunResults("r", {"model": {"latent_bank": True, "pose_vae": vae}, **changes})

    assert run(True, preprocess={"train_offsets": [1, 2, 3]}).configuration == "full, offsets 1/2/3"
    assert run(True, loss={"geometry_weight": "0.5"}).configuration == "full, geometry 0.5"
    assert run(False, preprocess={"train_offsets": [1, 2]}, loss={"geometry_weight": 0.5}).configuration == \
        "no-vae, offsets 1/2, geometry 0.5"
    assert run(True, preprocess={"train_offsets": None}, loss={"geometry_weight": 0.0}).configuration == "full"
    assert run(True, train={"time_reversal": "0.5"}).configuration == "full, reversed 0.5"


def test_vae_study_rows_follow_the_four_configurations_and_are_compared_with_the_full_model():
    runs = [study_run("beta-s0", 0, 0.20, beta=1e-3), study_run("beta-s1", 1, 0.22, beta=1e-3),
            study_run("full-s0", 0, 0.10), study_run("full-s1", 1, 0.12),
            study_run("mean-s0", 0, 0.11, sample=False), study_run("mean-s1", 1, 0.13, sample=False),
            study_run("small-s0", 0, 0.12, beta=1e-6)]
    text = format_report(runs)
    rows = table_rows(text[text.index("### simcol_12"):text.index("### Pose against constant velocity")])
    # the ablation first, then beta in numeric order (1e-06 before 0.001), then the mean warp
    assert [row[0] for row in rows[2:]] == [
        "full", "full, β=1e-06", "full, β=0.001", "full, mean warp", "trivial baseline",
        "full, β=1e-06 - full", "full, β=0.001 - full", "full, mean warp - full"]
    assert rows[-2][:3] == ["full, β=0.001 - full", "2", "+0.1000 *"]
    assert rows[-1][:3] == ["full, mean warp - full", "2", "+0.0100"]


def test_the_sweep_runs_dvc_with_this_interpreters_folder_first_on_path(tmp_path, monkeypatch):
    """Stage commands call `python`: the queue worker the sweep starts must find this environment's, also when
    it is not activated."""
    import subprocess
    import sys

    from endoflow import sweep

    calls = []
    monkeypatch.setenv("PATH", "/usr/bin")
    monkeypatch.setattr(subprocess, "run", lambda command, cwd, env: calls.append((command, env))
                        or subprocess.CompletedProcess(command, 0))
    (tmp_path / "params.yaml").write_text("")
    sweep.run_sweep(tmp_path, [0], start=True)
    assert calls[-1][0][-4:] == ["queue", "start", "-j", "1"] and len(calls) == 5
    assert all(env["PATH"].split(os.pathsep)[:2] == [str(Path(sys.executable).parent), "/usr/bin"]
               for _, env in calls)


def test_a_run_with_the_configuration_and_seed_of_another_but_other_params_is_left_out_loudly(capsys):
    full = study_run("full-s0", 0, 0.10)
    other = study_run("offset-s0", 0, 0.30)
    other.params["preprocess"] = {"neighbour_offset": 4}
    same = study_run("workspace", 0, 0.10)
    same.params["loss"]["kl_weight"] = "1e-05"  # as DVC's params read back: the same value
    # a key of a later commit, at its default: the run of the earlier commit lacks it and is the same
    same.params["train"] = {"time_reversal": 0.0}
    groups = runs_by_configuration([full, same, other, study_run("full-s1", 1, 0.12)])
    assert [run.name for run in groups["full"]] == ["full-s0", "full-s1"]
    error = capsys.readouterr().err
    assert error.count("left out") == 1
    assert "offset-s0 left out" in error and "full-s0" in error and "preprocess.neighbour_offset" in error


def test_seed_statistics_show_the_refined_path_and_the_scale_where_the_runs_have_them():
    runs = [seeded_run(f"full-s{seed}", True, True, seed, 0.10, 0.50) for seed in (0, 1)]
    for run, (refined, scale) in zip(runs, ((0.08, 0.9), (0.10, 1.1))):
        run.test_sets["simcol_12"]["pose_simcol"]["refined"] = {"rte": refined, "rot": 1.0}
        run.test_sets["simcol_12"]["scale"] = {"model": {"path_over_depth": scale, "depth_drift": 1.0}}
    text = format_report(runs)
    table = table_rows(text[text.index("### simcol_12"):text.index("### Pose against constant velocity")])
    assert "refined RTE (cm)" in table[0] and "path / depth scale (1)" in table[0]
    full = table[2]
    assert full[table[0].index("refined RTE (cm)")] == "0.0900 ± 0.0141"
    assert full[table[0].index("path / depth scale (1)")] == "1.0000 ± 0.1414"
    # a figure without a trivial baseline shows none
    assert table[3][table[0].index("path / depth scale (1)")] == "–"
    against = table_rows(text[text.index("### Pose against constant velocity"):])
    assert against[2][against[0].index("refined RTE (cm)")] == "-90.0 % *"  # 0.09 against constant velocity's 0.9
