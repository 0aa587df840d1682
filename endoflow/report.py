"""Markdown tables like the paper's Tables 1-3 from the evaluations of the workspace and of DVC's experiments and
commits (``endoflow report``; each protocol's table as :mod:`endoflow.evaluation.summary` lays it out).

With several seeds of a configuration, a last section gives per test set the mean ± sample standard deviation
over seeds (:data:`SEED_METRICS`), each configuration's difference from the full model (marked where it exceeds
the seed spread: ``|mean_a - mean_full| > sd_a + sd_full``) and its pose against constant velocity. A
configuration is the two ablation switches plus the studies' settings that differ from their defaults
(:data:`STUDY_SETTINGS`); runs of one configuration and seed count once, and one with other params is left out
with a note on stderr. How to run studies and read the report: docs/experiments.md.
"""

from __future__ import annotations

import functools
import json
import statistics
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Optional

from endoflow.config import LossConfig, ModelConfig, Params, PreprocessConfig, TrainConfig, flatten_params
from endoflow.evaluation.results import EVALUATION_FILE, HEADLINE, evaluation_path
from endoflow.evaluation.summary import PROTOCOL_TABLES, markdown_table, number_cell, protocol_table

# the paper's Table 3 rows: (name, model.latent_bank, model.pose_vae); `endoflow sweep` names its experiments so
ABLATIONS = (("full", True, True), ("no-bank", False, True), ("no-vae", True, False), ("neither", False, False))
DEFAULT_KL_WEIGHT = LossConfig().kl_weight
DEFAULT_POSE_SAMPLE = ModelConfig().pose_sample


@dataclass(frozen=True)
class StudySetting:
    """A training setting a study varies (docs/method.md, docs/results.md): a run whose value differs from the
    default is its own configuration, named after the ablation and this setting's label."""

    key: str  # dotted params key
    default: Any
    label: Callable[[Any], str]
    needs: Optional[str] = None  # the switch (dotted key) without which the setting does nothing: read as its default


# in the order configurations sort and name them
STUDY_SETTINGS = (
    StudySetting("model.pose_sample", DEFAULT_POSE_SAMPLE, lambda value: "mean warp", needs="model.pose_vae"),
    StudySetting("loss.kl_weight", DEFAULT_KL_WEIGHT, lambda value: f"β={value:g}", needs="model.pose_vae"),
    StudySetting("preprocess.train_offsets", PreprocessConfig().train_offsets,
                 lambda value: "offsets " + "/".join(str(offset) for offset in value)),
    StudySetting("loss.geometry_weight", LossConfig().geometry_weight, lambda value: f"geometry {value:g}"),
    StudySetting("train.time_reversal", TrainConfig().time_reversal, lambda value: f"reversed {value:g}"),
    StudySetting("loss.automask", LossConfig().automask, lambda value: "no automask"),
    StudySetting("loss.automask_pose", LossConfig().automask_pose, lambda value: "pose unmasked",
                 needs="loss.automask"),
    StudySetting("loss.automask_depth", LossConfig().automask_depth, lambda value: "depth unmasked",
                 needs="loss.automask"),
)
_SCHEMA_DEFAULTS = flatten_params(Params())
_HEADLINE_PROTOCOL = {metric: protocol for _, protocol, _, metric in HEADLINE}  # by the evaluation JSON's name
# the seed statistics' figures: column title, protocol of the evaluation JSON (the headline figures' own, the
# ATEs beside RTE's), the trivial baseline in it (None: the figure has none), and the method whose figure it is
# with its metric's key (the model's own, or its path refined against keyframes)
SEED_METRICS = {"abs_rel": ("Abs Rel", _HEADLINE_PROTOCOL["abs_rel"], "constant_depth", ("model", "abs_rel")),
                "rte": ("RTE (cm)", _HEADLINE_PROTOCOL["rte"], "constant_velocity", ("model", "rte")),
                "rot": ("ROT (°)", _HEADLINE_PROTOCOL["rot"], "constant_velocity", ("model", "rot")),
                "ate": ("ATE (cm)", _HEADLINE_PROTOCOL["rte"], "constant_velocity", ("model", "ate")),
                "ate_local": ("ATE local (cm)", _HEADLINE_PROTOCOL["rte"], "constant_velocity", ("model", "ate_local")),
                "step_corr": ("step corr (↑)", "pose_motion", "constant_velocity", ("model", "step_corr")),
                "far_ratio": ("far GT/pred (1)", _HEADLINE_PROTOCOL["abs_rel"], None, ("model", "far_ratio")),
                "path_over_depth": ("path / depth scale (1)", "scale", None, ("model", "path_over_depth")),
                "depth_drift": ("depth scale drift (1)", "scale", None, ("model", "depth_drift")),
                "refined_rte": ("refined RTE (cm)", "pose_simcol", "constant_velocity", ("refined", "rte")),
                "refined_rot": ("refined ROT (°)", "pose_simcol", "constant_velocity", ("refined", "rot"))}
POSE_TARGET_METRICS = ("rte", "rot", "ate", "ate_local", "refined_rte", "refined_rot")


@dataclass
class RunResults:
    """One run (workspace, commit or experiment): its label and ``{test set: metrics JSON}``."""

    name: str
    params: dict[str, Any] = field(default_factory=dict)
    test_sets: dict[str, dict] = field(default_factory=dict)

    @property
    def configuration(self) -> Optional[str]:
        """The configuration's name: the ablation's (``full``, ``no-bank``, ``no-vae``, ``neither``) followed by the
        labels of the :data:`STUDY_SETTINGS` that differ from their defaults (``full, mean warp``,
        ``full, β=0.001``, ``full, offsets 1/2/3``); None for a run without the two switches."""
        key = self.configuration_key
        if key is None:
            return None
        values = self.study_values()
        labels = [setting.label(values[setting.key]) for setting in STUDY_SETTINGS
                  if values[setting.key] != setting.default]
        return ", ".join([ABLATIONS[key[1]][0]] + labels)

    def param(self, key: str, default: Any) -> Any:
        """The run's value of the dotted ``key`` (``default`` where its params lack it)."""
        section, name = key.split(".")
        return self.params.get(section, {}).get(name, default)

    @property
    def configuration_key(self) -> Optional[tuple[bool, int, tuple[Any, ...]]]:
        """(a study setting differs from its default, index in :data:`ABLATIONS`, the settings in a sortable form):
        sorts the four ablations first, in the paper's order, then the studies' configurations by their settings
        (a switch after its default, numbers in numeric order)."""
        model = self.params.get("model", {})
        if "latent_bank" not in model or "pose_vae" not in model:
            return None
        switches = (bool(model["latent_bank"]), bool(model["pose_vae"]))
        ablation = [(bank, vae) for _, bank, vae in ABLATIONS].index(switches)
        values = self.study_values()
        differs = any(values[setting.key] != setting.default for setting in STUDY_SETTINGS)
        return differs, ablation, tuple(_sortable(values[setting.key], setting.default) for setting in STUDY_SETTINGS)

    def study_values(self) -> dict[str, Any]:
        """Each study setting's value in the run's params (its default where the params lack it, or where the switch
        it needs is off: the pose VAE, auto-masking)."""
        values = {}
        for setting in STUDY_SETTINGS:
            value = self.param(setting.key, setting.default)
            if setting.needs is not None and not self.param(setting.needs, _SCHEMA_DEFAULTS[setting.needs]):
                value = setting.default
            elif isinstance(setting.default, float):
                value = _float_or(value, setting.default)
            values[setting.key] = value
        return values

    @property
    def label(self) -> str:
        model = self.params.get("model", {})
        switches = [f"{text} {'on' if model[key] else 'off'}" for key, text in
                    (("latent_bank", "bank"), ("pose_vae", "VAE")) if key in model]
        return f"{self.name} ({', '.join(switches)})" if switches else self.name


@functools.lru_cache(maxsize=1)
def _default_flat_params() -> dict[str, Any]:
    return flatten_params(Params())


def _sortable(value: Any, default: Any) -> Any:
    """A study setting's value as something runs sort by: a switch as whether it is off its default, a number as
    itself, a list (or null) as a tuple."""
    if isinstance(default, bool):
        return value != default
    if isinstance(default, float):
        return value
    return tuple(value or ())


def _float_or(value: Any, default: float) -> float:
    """``value`` as a number (DVC writes ``1e-05``, which YAML 1.1 reads as a string), else ``default``."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return default


class ExperimentsUnavailable(Exception):
    """DVC's experiments cannot be listed here; the message says why."""


def workspace_results(predictions_dir: str | Path, params: Optional[dict] = None,
                      running: Optional[str] = None) -> RunResults:
    """The workspace's full evaluations (``<predictions_dir>/<test set>/evaluation.json``); ``running`` names a
    DVC experiment running in the workspace, whose results may be partial."""
    folder = Path(predictions_dir)
    test_sets = {path.parent.name: json.loads(path.read_text())
                 for path in sorted(folder.glob(f"*/{EVALUATION_FILE}"))}
    name = f"workspace: {running} running, partial" if running else "workspace"
    return RunResults(name, params or {}, test_sets)


def dvc_experiment_states(project_root: str | Path, all_commits: bool = False) -> list[dict]:
    """What ``dvc exp show --json`` prints (baseline commits, each with its experiments: HEAD's, or with
    ``all_commits`` every commit's, as ``-A``), through DVC's Python API, so that it works without ``dvc`` on
    ``PATH``; :class:`ExperimentsUnavailable` says why it cannot."""
    try:
        from dvc.exceptions import DvcException, NotDvcRepoError
        from dvc.repo import Repo
    except ImportError as exc:
        raise ExperimentsUnavailable(f"DVC cannot be imported by {sys.executable} ({exc}): run endoflow from the "
                                     f"environment it was installed into") from exc
    try:
        with Repo(str(project_root)) as repo:
            states = repo.experiments.show(all_commits=all_commits, hide_queued=True, hide_failed=True)
            return [state.dumpd() for state in states]
    except NotDvcRepoError as exc:
        raise ExperimentsUnavailable(f"{Path(project_root).resolve()} is not a DVC project") from exc
    except DvcException as exc:
        raise ExperimentsUnavailable(f"DVC could not list the experiments: {exc}") from exc


def running_in_workspace(states: list[dict]) -> Optional[str]:
    """The name of the DVC experiment running in the workspace, if one is."""
    for state in states:
        for group in state.get("experiments") or []:
            executor = group.get("executor") or {}
            if executor.get("state") == "running" and executor.get("name") == "workspace":
                return group.get("name") or "?"
    return None


def experiment_results(states: list[dict], project_root: str | Path, predictions_dir: str,
                       read: Optional[Callable[[str, str], Optional[str]]] = None) -> list[RunResults]:
    """Baseline commits and finished experiments that have evaluations, each read at its revision (``read(rev,
    path)`` gives a file's text there or ``None``; default: DVC's file system, which reads outputs from the
    cache)."""
    read = read or _dvc_reader(project_root)
    runs = []
    for state in _finished_states(states):
        rev = state.get("rev")
        if not rev or rev == "workspace":
            continue
        data = state.get("data") or {}
        params = ((data.get("params") or {}).get("params.yaml") or {}).get("data") or {}
        test_sets = {}
        for test_set in (params.get("eval") or {}).get("test_sets") or {}:
            text = read(rev, str(evaluation_path(predictions_dir, test_set)))
            if text is not None:
                test_sets[test_set] = json.loads(text)
        if test_sets:
            runs.append(RunResults(state.get("name") or str(rev)[:7], params, test_sets))
    return runs


def _finished_states(states: Iterable[dict]) -> Iterable[dict]:
    for state in states:
        yield state
        for group in state.get("experiments") or []:
            if (group.get("executor") or {}).get("state") in (None, "success"):
                yield from _finished_states(group.get("revs") or [])


def _dvc_reader(project_root: str | Path) -> Callable[[str, str], Optional[str]]:
    from dvc.api import DVCFileSystem

    @functools.lru_cache(maxsize=None)
    def file_system(rev: str) -> DVCFileSystem:  # opening a revision reads its tree: once per revision
        return DVCFileSystem(str(project_root), rev=rev)

    def read(rev: str, path: str) -> Optional[str]:
        fs = file_system(rev)
        try:
            return fs.read_text(path) if fs.exists(path) else None
        except FileNotFoundError:  # listed in the revision's dvc.lock, but gone from this cache
            return None

    return read


def format_report(runs: list[RunResults], order: Iterable[str] = ()) -> str:
    """Markdown: per test set (those in ``order`` first), the paper depth protocol (Table 1 style), the
    SimCol3D challenge depth protocol, and pose (Table 2 style); then an ablation summary (Table 3 style)."""
    if not runs:
        return "No evaluation metrics found: run `dvc repro` (or `dvc exp run`) first.\n"
    found = {name for run in runs for name in run.test_sets}
    test_sets = [name for name in order if name in found] + sorted(found - set(order))
    sections = []
    for test_set in test_sets:
        parts = [f"## {test_set}"]
        for title, protocol, columns in PROTOCOL_TABLES:
            table = protocol_table([(run.label, run.test_sets.get(test_set, {}).get(protocol)) for run in runs],
                                   columns)
            if table:
                parts.append(f"### {title}\n\n{table}")
        sections.append("\n\n".join(parts))
    sections.append("## Ablation summary\n\n" + ablation_table(runs, test_sets))
    seeds = seed_statistics(runs, test_sets)
    if seeds:
        sections.append(seeds)
    return "\n\n".join(sections) + "\n"


def runs_by_configuration(runs: list[RunResults]) -> dict[str, list[RunResults]]:
    """Runs of each known configuration, one per seed (the first run of a configuration and seed), in the order
    of :attr:`RunResults.configuration_key`."""
    groups: dict[str, dict[Any, RunResults]] = {}
    known = sorted((run for run in runs if run.configuration_key is not None), key=lambda run: run.configuration_key)
    for run in known:
        seed = run.params.get("seed")
        kept = groups.setdefault(run.configuration, {}).setdefault(seed, run)
        differing = _differing_params(kept.params, run.params) if kept is not run else []
        if differing:
            print(f"endoflow report: {run.name} left out of the seed statistics: {kept.name} has its configuration "
                  f"({run.configuration}) and seed ({seed}) but other params ({', '.join(differing)})",
                  file=sys.stderr)
    return {name: list(by_seed.values()) for name, by_seed in groups.items()}


def _differing_params(first: dict, second: dict) -> list[str]:
    """Dotted keys whose values differ, compared as text (DVC's params give ``1e-05`` as a string); a key one run's
    params lack reads as its default (a run of a commit from before the key existed)."""
    defaults = _default_flat_params()
    flat_first, flat_second = {**defaults, **flatten_params(first)}, {**defaults, **flatten_params(second)}
    return sorted(key for key in flat_first.keys() | flat_second.keys()
                  if str(flat_first.get(key)) != str(flat_second.get(key)))


def seed_samples(runs: list[RunResults], test_set: str, metric: str) -> list[float]:
    """The model's ``metric`` (a key of :data:`SEED_METRICS`) on ``test_set`` in each run that has it."""
    _, protocol, _, (method, key) = SEED_METRICS[metric]
    values = [run.test_sets.get(test_set, {}).get(protocol, {}).get(method, {}).get(key) for run in runs]
    return [float(value) for value in values if isinstance(value, (int, float))]


def trivial_baseline(runs: list[RunResults], test_set: str, metric: str) -> Optional[float]:
    """The figure's trivial baseline (the same in every run: it depends on the data only); None for a figure
    without one."""
    _, protocol, method, (_, key) = SEED_METRICS[metric]
    if method is None:
        return None
    for run in runs:
        value = run.test_sets.get(test_set, {}).get(protocol, {}).get(method, {}).get(key)
        if isinstance(value, (int, float)):
            return float(value)
    return None


def mean_sd(values: list[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (0 for a single value)."""
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else 0.0


def seed_statistics(runs: list[RunResults], test_sets: list[str]) -> str:
    """Markdown: per test set, each configuration's mean +- sd over seeds, the trivial baselines and each
    ablation's difference from the full model (``*``: beyond the seed spread); then every configuration's pose
    against constant velocity. Empty unless a configuration has 2 seeds."""
    groups = runs_by_configuration(runs)
    if not any(len(group) > 1 for group in groups.values()):
        return ""
    parts = ["## Seed statistics\n\nMean ± sample standard deviation over seeds; lower is better for every "
             "figure but the step correlation (↑: 1 follows every change of the camera's speed, 0 none) and the "
             "ratios marked (1), best at 1: the path's scale over the depth's (one scale for both, as a map "
             "needs), the depth scale's drift along a sequence and the far depth's GT over prediction (above 1: "
             "the far end compressed). Trivial "
             "baselines: constant depth for Abs Rel, constant velocity for pose. Differences are of the means from "
             "the full model, marked `*` where they exceed the seed spread (the mean ± sd intervals do not "
             "overlap)."]
    for test_set in test_sets:
        metrics = [m for m in SEED_METRICS if any(seed_samples(group, test_set, m) for group in groups.values())]
        if metrics:
            parts.append(f"### {test_set}\n\n" + _seed_table(runs, groups, test_set, metrics))
    pose = _pose_against_constant_velocity(runs, groups, test_sets)
    if pose:
        parts.append(pose)
    return "\n\n".join(parts)


def _seed_table(runs: list[RunResults], groups: dict[str, list[RunResults]], test_set: str,
                metrics: list[str]) -> str:
    headers = ["configuration", "seeds"] + [SEED_METRICS[m][0] for m in metrics]
    rows = []
    for name, group in groups.items():
        cells = []
        for metric in metrics:
            values = seed_samples(group, test_set, metric)
            cells.append("{:.4f} ± {:.4f}".format(*mean_sd(values)) if values else "–")
        rows.append([name, str(len(group))] + cells)
    rows.append(["trivial baseline", "–"] + [number_cell(trivial_baseline(runs, test_set, m)) for m in metrics])
    for name, group in groups.items():
        if name == "full" or "full" not in groups:
            continue
        cells = []
        for metric in metrics:
            full, other = seed_samples(groups["full"], test_set, metric), seed_samples(group, test_set, metric)
            if not full or not other:
                cells.append("–")
                continue
            (full_mean, full_sd), (mean, sd) = mean_sd(full), mean_sd(other)
            # a single seed has no spread to compare with
            beyond = min(len(full), len(other)) > 1 and abs(mean - full_mean) > sd + full_sd
            cells.append(f"{mean - full_mean:+.4f}{' *' if beyond else ''}")
        rows.append([f"{name} - full", str(len(group))] + cells)
    return markdown_table(headers, rows)


def _pose_against_constant_velocity(runs: list[RunResults], groups: dict[str, list[RunResults]],
                                    test_sets: list[str]) -> str:
    """Per configuration and test set, each pose figure's mean relative to constant velocity's; ``*`` where the
    model is better by more than its seed spread (constant velocity depends on the data only: no spread)."""
    shown = [m for m in POSE_TARGET_METRICS
             if any(seed_samples(group, t, m) for group in groups.values() for t in test_sets)]
    baselines = {(t, m): trivial_baseline(runs, t, m) for t in test_sets for m in shown}
    rows = []
    for name, group in groups.items():
        for test_set in test_sets:
            cells = []
            for metric in shown:
                values, baseline = seed_samples(group, test_set, metric), baselines[test_set, metric]
                if not values or not baseline:
                    cells.append("–")
                    continue
                mean, sd = mean_sd(values)
                beyond = len(values) > 1 and mean + sd < baseline
                cells.append(f"{100 * (mean / baseline - 1):+.1f} %{' *' if beyond else ''}")
            if any(cell != "–" for cell in cells):
                rows.append([name, test_set, str(len(group))] + cells)
    if not rows:
        return ""
    headers = ["configuration", "test set", "seeds"] + [SEED_METRICS[m][0] for m in shown]
    return ("### Pose against constant velocity\n\nThe mean over seeds relative to constant velocity's figure "
            "(negative: the model is better); `*` where the model is better by more than its seed spread "
            "(mean + sd below constant velocity's).\n\n" + markdown_table(headers, rows))


def ablation_table(runs: list[RunResults], test_sets: list[str]) -> str:
    """One row per run: Abs Rel (paper protocol) and RTE (challenge protocol) on every test set."""
    headers = ["run"] + [f"{t} {m}" for t in test_sets for m in ("Abs Rel", "RTE")]
    rows = []
    for run in runs:
        row = [run.label]
        for test_set in test_sets:
            metrics = run.test_sets.get(test_set, {})
            row.append(number_cell(metrics.get("depth_paper", {}).get("model", {}).get("abs_rel")))
            row.append(number_cell(metrics.get("pose_simcol", {}).get("model", {}).get("rte")))
        rows.append(row)
    return markdown_table(headers, rows)


def build_report(project_root: str | Path, predictions_dir: str, params: Optional[dict] = None,
                 experiments: bool = True, all_commits: bool = False) -> str:
    """The whole report for a project: the workspace's evaluations plus, if asked, those of DVC's baseline
    commits and experiments, HEAD's or every commit's (a note on stderr says why when DVC cannot list them)."""
    root = Path(project_root)
    states: list[dict] = []
    if experiments:
        try:
            states = dvc_experiment_states(root, all_commits)
        except ExperimentsUnavailable as exc:
            print(f"endoflow report: workspace only: {exc}", file=sys.stderr)
    runs = []
    workspace = workspace_results(root / predictions_dir, params, running_in_workspace(states))
    if workspace.test_sets:
        runs.append(workspace)
    runs += experiment_results(states, root, predictions_dir) if states else []
    return format_report(runs, order=((params or {}).get("eval") or {}).get("test_sets") or ())
