"""The paper preset, whole, as a dry run: `presets/paper.yaml` with only the cuts a CPU run needs, through
`dvc repro` in a fresh copy of the project.

The cuts (:data:`DRY_RUN_CUTS`) point the data at a few synthetic sequences, which preprocessing brings to the
paper's 480x480 (as it brings real SimCol3D's 475 px frames), and shorten every loop to a step or two on 2 CPU cores; the architecture (the released code's bank scale), the losses,
the optimiser, the precision and the devices stay the paper's. So a shape, config or device mistake on the paper's
path fails here, on CPU. The run's wall time, CPU time and peak memory per stage are printed and written to
``dry_run_resources.json`` beside the run's folder.
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import threading
import time
from pathlib import Path
from typing import Iterable

import psutil  # a requirement of dvc, which the pipeline runs on
import pytest
import yaml

from endoflow.config import load_params, params_from_dict, params_to_dict
from endoflow.evaluation.results import evaluation_path
from endoflow.io import load_plain_torch_file
from endoflow.models.endoflow_model import generator_spec
from endoflow.models.model_file import load_model_file
from tests.module_temp import ModuleTemp
from tests.project_clone import PROJECT, clone_project, pipeline_env

PAPER = PROJECT / "presets" / "paper.yaml"
PAPER_RAW = params_to_dict(load_params(PAPER))  # the full set: the preset over the defaults


def preset_entries(section: dict, names: list[str]) -> dict:
    """The entries ``names`` of a named section of the preset (test sets, sequences), as the preset has them."""
    return {name: section[name] for name in names}


# Everything the dry run changes in presets/paper.yaml, and nothing else.
DRY_RUN_CUTS = {
    # the synthetic renders (stage `synthesize`) instead of the real datasets. They stay at the renderer's own size:
    # preprocessing resizes every frame to the paper's 480x480, and rendering at 480 px took 1.6 of the run's 7.7 min
    "data.simcol.root": "data/raw/synthetic/SimCol3D",
    "data.endoslam.root": "data/raw/synthetic/EndoSLAM",
    "data.scenenet.root": "data/raw/synthetic/SceneNet",
    # 5 sequences per SimCol scene: S1-S3/B1-B3 train, S4/B4 are the preset's val, S5/B5 (and O1-O3) its test;
    # 3 frames, the fewest that give a triplet (one sample per sequence)
    "synth.simcol.sequences": 5,
    "synth.simcol.frames": 3,
    "synth.simcol.test_frames": 3,
    "synth.endoslam.frames": 3,  # the preset's 2 sequences stay: Colon and Small Intestine, one test set each
    "synth.scenenet.sequences": 2,  # 6 depth maps: 5 to train the bank on, 1 held out for the SWD
    "synth.scenenet.frames": 3,
    "synth.video.frames": 3,  # the built-in unlabelled video (the paper preset does not train on it)
    "preprocess.workers": 2,
    # one generator step per resolution and one training step, both of batch 2 (validation, 2 samples, is then
    # one batch, and evaluation sees one target frame per sequence: train.val_batches and
    # eval.max_frames_per_sequence need no cut)
    "latent_bank.steps_per_stage": 1,
    "latent_bank.batch_size": 2,
    "train.epochs": 1,
    "train.steps_per_epoch": 1,
    "train.batch_size": 2,
    # one Ray worker on this machine's 2 CPU cores, one loader process beside its training process
    "ray.use_gpu": False,
    "ray.cpus_per_worker": 2.0,
    "train.loader_workers": 1,
    # the reconstruct stage fuses six surfaces per sequence: at 480 px the default voxel (the pixel footprint,
    # 0.022 cm) costs minutes on 2 cores, and a coarse one runs the same code
    "reconstruct.voxel_cm": 0.2,
    # the refined path's Gauss-Newton at 480 px: two steps per level run the same code as twelve
    "refine.iterations": 2,
    # one test set per dataset, each of one sequence, and one reconstructed sequence: the others run the same code
    # on other frames, and the paper's networks take about 6 s a frame at 480 px on 2 cores without AVX-512
    "eval.test_sets": {"simcol_12": {**PAPER_RAW["eval"]["test_sets"]["simcol_12"], "groups": ["SyntheticColon_I"]},
                       **preset_entries(PAPER_RAW["eval"]["test_sets"], ["endoslam_colon"])},
    "reconstruct.sequences": preset_entries(PAPER_RAW["reconstruct"]["sequences"], ["simcol_S5"]),
}


def paper_dry_run_params(cuts: dict = DRY_RUN_CUTS) -> dict:
    """presets/paper.yaml over the defaults with ``cuts`` (dotted key -> value) applied; every cut key must exist."""
    raw = copy.deepcopy(PAPER_RAW)
    for key, value in cuts.items():
        section, leaf = parent_section(raw, key)
        assert leaf in section, f"dry-run cut {key} is not a key of the params"
        section[leaf] = value
    return raw


def parent_section(tree: dict, key: str) -> tuple[dict, str]:
    """The section of ``tree`` holding the dotted ``key``, and the key's last part."""
    *parents, leaf = key.split(".")
    for name in parents:
        tree = tree[name]
    return tree, leaf


def without(tree: dict, keys: Iterable[str]) -> dict:
    """A copy of ``tree`` without the dotted ``keys``."""
    tree = copy.deepcopy(tree)
    for key in keys:
        section, leaf = parent_section(tree, key)
        del section[leaf]
    return tree


class StageMonitor:
    """Samples the process tree under ``dvc repro`` and records, per stage script, its wall time (first to last
    sighting), CPU time (user + system of every process of the stage, Ray's included, as last seen) and peak
    memory: the summed RSS of the stage's processes (an upper bound, as pages shared between them count twice)
    and the RSS of its largest process.

    CPU time is the figure to compare between machines and runs: on a busy machine the wall time grows, it does not.
    """

    # Each sample walks the process tree: every 0.2 s it took 7.5 % of a core with 22 processes under it (70 s of
    # CPU over a run, taken from the run it measures), every second 1.5 %. Stages last 6 s and more.
    INTERVAL_S = 1.0

    def __init__(self, root_pid: int) -> None:
        self.root = psutil.Process(root_pid)
        self.stages: dict[str, dict] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()

    def stop(self) -> dict[str, dict[str, float]]:
        self._stop.set()
        self._thread.join()
        return {
            name: {
                "wall_seconds": round(s["last"] - s["first"], 1),
                "cpu_seconds": round(sum(s["cpu"].values()), 1),
                "peak_rss_gib": round(s["peak"] / 2**30, 2),
                "peak_rss_largest_process_gib": round(s["largest"] / 2**30, 2),
            }
            for name, s in self.stages.items()
        }

    def _sample(self) -> None:
        while not self._stop.wait(self.INTERVAL_S):
            try:
                descendants = self.root.children(recursive=True)
            except psutil.Error:
                return
            for process in descendants:
                name = self._stage_name(process)
                if name is not None:
                    self._record(name, process)

    @staticmethod
    def _stage_name(process: psutil.Process) -> str | None:
        """``preprocess@simcol`` for a process running ``python -m stages.preprocess simcol``, else None."""
        try:
            args = process.cmdline()
        except psutil.Error:
            return None
        modules = [i for i, arg in enumerate(args) if arg.startswith("stages.") and i > 0 and args[i - 1] == "-m"]
        if not modules or "python" not in Path(args[0]).name:
            return None
        i = modules[0]
        stem = args[i].removeprefix("stages.")
        return f"{stem}@{args[i + 1]}" if i + 1 < len(args) else stem

    def _record(self, name: str, process: psutil.Process) -> None:
        now = time.monotonic()
        stage = self.stages.setdefault(name, {"first": now, "last": now, "peak": 0, "largest": 0, "cpu": {}})
        total = 0
        for member in [process, *self._children(process)]:
            try:
                with member.oneshot():
                    rss = member.memory_info().rss
                    cpu = member.cpu_times()
            except psutil.Error:
                continue
            total += rss
            stage["largest"] = max(stage["largest"], rss)
            stage["cpu"][member.pid] = cpu.user + cpu.system
        stage["last"], stage["peak"] = now, max(stage["peak"], total)

    @staticmethod
    def _children(process: psutil.Process) -> list[psutil.Process]:
        try:
            return process.children(recursive=True)
        except psutil.Error:
            return []


def run_paper_dry_run(clone: Path, cuts: dict = DRY_RUN_CUTS) -> dict:
    """Copy the project to ``clone`` with the paper params cut by ``cuts``, run `dvc repro` there; returns its
    resources."""
    env = pipeline_env("dry-run")
    clone_project(clone, yaml.safe_dump(paper_dry_run_params(cuts), sort_keys=False), env)
    started = time.monotonic()
    log = clone / "dvc_repro.log"
    with log.open("w") as out:
        repro = subprocess.Popen(["dvc", "repro"], cwd=clone, env=env, stdout=out, stderr=subprocess.STDOUT)
        monitor = StageMonitor(repro.pid)
        # wait4, not Popen.wait: its rusage is this run's alone (the test session's other children are not in it)
        _, status, usage = os.wait4(repro.pid, 0)
        repro.returncode = os.waitstatus_to_exitcode(status)
    stages = monitor.stop()
    assert repro.returncode == 0, f"dvc repro failed:\n{log.read_text()[-8000:]}"
    resources = {
        "wall_seconds": round(time.monotonic() - started, 1),
        # the largest single process of the run (a stage script, or dvc): Linux reports the maximum over the
        # waited-for descendants
        "max_rss_one_process_gib": round(usage.ru_maxrss / 2**20, 2),
        "stages": stages,
    }
    (clone / "dry_run_resources.json").write_text(json.dumps(resources, indent=2))
    print(f"\npaper dry run: {json.dumps(resources, indent=2)}")
    return resources


# The run takes a few minutes on 2 idle cores, far longer on a busy machine: the limit is the suite's, doubled.
DRY_RUN_TIMEOUT_S = 1800


@pytest.fixture(scope="module")
def paper_repro(module_tmp: ModuleTemp) -> tuple[Path, dict]:
    # The run leaves about 3.6 GB (renders, shards, DVC's cache, banks, checkpoints, MLflow's copies): module_tmp
    # removes it when the module passes and keeps it when a test failed.
    clone = module_tmp("paper") / "endoflow"
    return clone, run_paper_dry_run(clone)


def test_the_cut_paper_preset_validates_and_differs_from_the_paper_only_in_the_cuts():
    cut = params_to_dict(params_from_dict(paper_dry_run_params()))
    paper = params_to_dict(load_params(PAPER))
    assert without(cut, DRY_RUN_CUTS) == without(paper, DRY_RUN_CUTS)
    for key in DRY_RUN_CUTS:
        (cut_section, leaf), (paper_section, _) = parent_section(cut, key), parent_section(paper, key)
        assert cut_section[leaf] != paper_section[leaf], f"the cut {key} leaves the preset's value"
    assert cut["data"]["size"] == 480


@pytest.mark.slow
@pytest.mark.timeout(DRY_RUN_TIMEOUT_S)
def test_every_stage_of_the_paper_pipeline_writes_its_outputs(paper_repro):
    clone, _ = paper_repro
    params = load_params(clone / "params.yaml")
    for dataset in ("simcol", "endoslam", "scenenet"):
        shards = clone / params.preprocess.out / dataset
        assert (shards / "manifest.parquet").is_file()
        assert list(shards.glob("*.tar"))
    for path in (params.latent_bank.out, params.latent_bank.metrics, params.train.out, params.train.metrics):
        assert (clone / path).is_file(), path
    for test_set in params.eval.test_sets:
        evaluation = json.loads(evaluation_path(clone / params.eval.predictions, test_set).read_text())
        assert evaluation["frames"] > 0, test_set
        headline = json.loads((clone / params.eval.metrics / f"{test_set}.json").read_text())[f"test_{test_set}"]
        assert set(headline) == {"abs_rel", "rte_cm", "rot_deg"}, test_set
        assert any((clone / params.eval.predictions / test_set).rglob("*.npy")), test_set


@pytest.mark.slow
@pytest.mark.timeout(DRY_RUN_TIMEOUT_S)
def test_the_trained_model_carries_the_paper_architecture(paper_repro):
    clone, _ = paper_repro
    params = load_params(clone / "params.yaml")
    paper = load_params(PAPER)
    bank = load_plain_torch_file(clone / params.latent_bank.out, "the dry run's latent bank")
    assert bank["spec"] == generator_spec(paper).to_dict()
    record = load_model_file(clone / params.train.out)
    assert generator_spec(record.params) == generator_spec(paper)
    assert (record.params.model, record.params.loss) == (paper.model, paper.loss)
    frozen = sum(tensor.numel() for name, tensor in record.state.items() if name.startswith("depth_net.bank."))
    assert frozen > 70e6  # the released code's scale (75.8 M), not the laptop default's 0.57 M


@pytest.mark.slow
@pytest.mark.timeout(DRY_RUN_TIMEOUT_S)
def test_the_dry_run_records_time_and_peak_memory_of_every_stage(paper_repro):
    clone, resources = paper_repro
    params = load_params(clone / "params.yaml")
    expected = {"synthesize", "pretrain_latent_bank", "train", *(f"preprocess@{d}" for d in ("simcol", "endoslam",
                "scenenet", "video")), *(f"evaluate@{name}" for name in params.eval.test_sets),
                *(f"reconstruct@{name}" for name in params.reconstruct.sequences)}
    assert set(resources["stages"]) == expected
    assert resources["max_rss_one_process_gib"] > 0
    for stage in resources["stages"].values():
        assert 0 < stage["peak_rss_largest_process_gib"] <= stage["peak_rss_gib"]
        assert stage["cpu_seconds"] > 0 and stage["wall_seconds"] >= 0
