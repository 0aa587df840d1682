"""Evaluation frames/s of an earlier version of the code against this one: the whole ``evaluate_test_set``, in one run.

    python benchmarks/bench_evaluate.py --baseline DIR [--preset params.yaml] [--device auto] [--threads T]
                                        [--sequences 2] [--frames F] [--rounds 2] [--loader-workers W]
                                        [--refine] [--candidate DIR]

``DIR`` holds the earlier ``endoflow`` package (``git archive <commit> endoflow | tar -x -C DIR``); ``after`` is
this tree's (``--candidate``: another folder holding one). Shards: the real SimCol3D sample's frames repeated into
``--sequences`` test sequences of ``--frames`` frames (``bench_preprocess.repeated_sample_layout``), preprocessed
by the real ``preprocess_dataset`` at the preset's ``data.size``, as ``bench_loader.py`` writes them: 64 px with
``params.yaml``, 480 px with ``presets/paper.yaml``. Model: the preset's, initialised from ``seed`` (its latent
bank random: the compute of a trained one), written as a model file by each side's own code.

Each measurement is a fresh process (``PYTHONPATH``: the side's folder) timing two ``evaluate_test_set`` calls on
every frame, each reading the shards, decoding, running the networks, scoring and writing predictions, tables and
plots (model loading included): ``cold``, the first, as the evaluate stage runs in a process of its own (CUDA and
cuDNN start on its first batches, which a short test set does not amortise), and ``warm``, the same call again, as
the frames of a long test set go. The sides alternate, before after before after (``--rounds``), so that load
from other processes hits both alike; the medians of the rounds are printed: frames/s of the whole call, the
stage's own figure (``evaluation.json``'s ``frames_per_second``, from after the model is loaded to the last frame
scored: what the evaluate stage reports), and after/before. Then whether both sides wrote the same tables and
prediction files in the last call, bit for bit (the timing aside).

Settings: the preset's (keys the earlier schema lacks left out), with ``eval.device`` ``--device``, ``threads``
``--threads`` (torch's CPU threads), ``train.loader_workers`` ``--loader-workers`` (``before`` reads in one
process whatever it says). The refined path (``refine.enabled``) is left out unless ``--refine``: its tracker runs
on the CPU in float64, seconds per 480 px frame with an untrained model's depth, the same before and after, and
would hide everything else. Defaults: ``--frames`` 100 on CUDA, 60 on a CPU at up to 128 px and 10 above.
Figures are printed, not asserted: they depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from code_versions import environment_importing

ROOT = Path(__file__).resolve().parents[1]
SIDES = ("before", "after")
CALLS = ("cold", "warm")
TEST_SET = "bench"


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", type=Path, required=True, help="folder holding the earlier endoflow package")
    parser.add_argument("--candidate", type=Path, default=ROOT, help="folder holding the endoflow measured after")
    parser.add_argument("--preset", type=Path, default=Path("params.yaml"))
    parser.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: the preset's)")
    parser.add_argument("--loader-workers", type=int, default=None,
                        help="loader processes after (default: the preset's train.loader_workers)")
    parser.add_argument("--sequences", type=int, default=2)
    parser.add_argument("--frames", type=int, default=None, help="frames per sequence (see the docstring)")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--refine", action="store_true", help="evaluate the refined path too (refine.enabled)")
    parser.add_argument("--worker", choices=(*SIDES, "shards"), help=argparse.SUPPRESS)
    parser.add_argument("--work", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--round", type=int, default=0, help=argparse.SUPPRESS)
    return parser.parse_args()


# ------------------------------------------------------------------------------------------ in a worker
def preset_params(args: argparse.Namespace):
    """The preset as this process's endoflow reads it (keys its schema lacks left out), set up for the run."""
    import yaml

    from endoflow.config import EvalSetConfig, Params, params_from_dict

    params = params_from_dict(known_keys(yaml.safe_load(args.preset.read_text()) or {}, Params))
    workers = params.train.loader_workers if args.loader_workers is None else args.loader_workers
    test_sets = {TEST_SET: EvalSetConfig(dataset="simcol")}
    return params.replace(
        threads=args.threads or params.threads, refine=params.refine.replace(enabled=args.refine),
        eval=params.eval.replace(device=args.device, shards=str(args.work / "shards"), test_sets=test_sets),
        # loader processes and the process reading them fit the CPUs a training worker reserves
        train=params.train.replace(loader_workers=workers),
        ray=params.ray.replace(cpus_per_worker=max(params.ray.cpus_per_worker, workers + 1.0)))


def known_keys(raw: dict, section: type) -> dict:
    """``raw`` without the keys ``section`` (a config section class) and the sections within it do not have."""
    known = {}
    for name, value in raw.items():
        if name not in section.model_fields:
            continue
        inner = section.model_fields[name].annotation
        nested = isinstance(inner, type) and hasattr(inner, "model_fields") and isinstance(value, dict)
        known[name] = known_keys(value, inner) if nested else value
    return known


def write_shards(args: argparse.Namespace) -> None:
    """The test shards of ``--sequences`` repeated-sample sequences at the preset's size, under ``<work>/shards``."""
    from bench_preprocess import SAMPLE, repeated_sample_layout
    from endoflow.data.shards import preprocess_dataset

    if not SAMPLE.is_dir():
        raise SystemExit(f"{SAMPLE}: the real SimCol3D sample is missing")
    params = preset_params(args)
    layout = args.work / "SimCol3D"
    repeated_sample_layout(layout, args.sequences, args.frames)
    names = [f"S{s}" for s in range(1, args.sequences + 1)]
    params.data.simcol = params.data.simcol.replace(root=str(layout), val=[], test=names)
    params.preprocess = params.preprocess.replace(samples_per_shard=16, shard_multiple=2,
                                                  workers=min(8, os.cpu_count() or 1))
    preprocess_dataset("simcol", params, args.work / "shards" / "simcol")


def evaluate_twice(args: argparse.Namespace) -> dict:
    """``cold`` and ``warm``: ``evaluate_test_set`` of every frame, timed, twice in this process; the model file is
    written first if this side has none."""
    import time

    import torch

    from endoflow.devices import resolve_device
    from endoflow.evaluation.evaluate import eval_set, eval_set_shards, evaluate_test_set

    params = preset_params(args)
    torch.set_num_threads(params.threads)
    model = args.work / f"model-{args.worker}.pt"
    if not model.is_file():
        write_model(params, model)
    urls = eval_set_shards(params.eval.shards, eval_set(params, TEST_SET))
    figures = {}
    for call in CALLS:
        out = args.work / f"{args.worker}-{args.round}-{call}"
        started = time.perf_counter()
        result = evaluate_test_set(params, TEST_SET, urls, model, out / "metrics.json", out / "plots",
                                   out / "predictions")
        figures[call] = {"fps": result["frames"] / (time.perf_counter() - started),
                         "stage_fps": result["frames_per_second"]}
    device = resolve_device(params.eval.device, "eval.device")
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"CPU, {params.threads} threads"
    return {**figures, "frames": result["frames"], "device": name, "loader_workers": params.train.loader_workers,
            "size": params.data.size, "batch": params.eval.batch_size, "precision": params.eval.precision}


def write_model(params, path: Path) -> None:
    """The preset's model from ``seed``, untrained, with flat training baselines."""
    import numpy as np
    import torch

    from endoflow.models.endoflow_model import build_model
    from endoflow.models.model_file import ModelRecord, TrainingBaselines, save_model_file

    torch.manual_seed(params.seed)
    model = build_model(params, None)
    size = params.data.size
    baselines = TrainingBaselines(mean_depth_cm=7.0, mean_depth_map=np.full((size, size), 7.0, np.float32),
                                  mean_relative_pose=np.eye(4))
    save_model_file(path, ModelRecord(params=params, state=model.state_dict(), epoch=0, val={"val_abs_rel": 1.0},
                                      mlflow_run_id=None, baselines=baselines))


# ------------------------------------------------------------------------------------------ in the driver
def run_worker(args: argparse.Namespace, role: str, tree: Path, round_index: int = 0) -> dict:
    """``role`` in a fresh process whose ``endoflow`` is the one in ``tree``; its figures (evaluations)."""
    env = environment_importing(tree)
    command = [sys.executable, __file__, "--worker", role, "--work", str(args.work), "--round", str(round_index),
               "--baseline", str(args.baseline), "--preset", str(args.preset), "--device", args.device,
               "--sequences", str(args.sequences), "--frames", str(args.frames)]
    command += ["--threads", str(args.threads)] if args.threads else []
    command += ["--loader-workers", str(args.loader_workers)] if args.loader_workers is not None else []
    command += ["--refine"] if args.refine else []
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"{role} failed:\n{done.stderr[-4000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1]) if role in SIDES else {}


def written_files(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` by its relative path; ``evaluation.json`` without its timing."""
    files = {str(path.relative_to(folder)): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}
    for name in [name for name in files if name.endswith("evaluation.json")]:
        figures = json.loads(files[name])
        figures.pop("frames_per_second", None)
        files[name] = json.dumps(figures, sort_keys=True).encode()
    return files


def compare_outputs(before: Path, after: Path) -> str:
    """Whether two runs wrote the same predictions and tables, and if not, how many files differ."""
    old, new = written_files(before), written_files(after)
    if sorted(old) != sorted(new):
        return f"different files: {sorted(set(old) ^ set(new))[:5]}"
    differing = [name for name in old if old[name] != new[name]]
    if not differing:
        return f"identical ({len(old)} files: tables, challenge depth and pose files, evaluation.json)"
    return f"{len(differing)} of {len(old)} files differ, e.g. {differing[:3]}"


def default_frames(args: argparse.Namespace) -> int:
    size = int(run_python(args, "from endoflow.config import load_params; import sys; "
                                "print(load_params(sys.argv[1]).data.size)", str(args.preset)))
    if args.device.startswith("cuda"):
        return 100
    return 60 if size <= 128 else 10


def run_python(args: argparse.Namespace, code: str, *argv: str) -> str:
    env = environment_importing(args.candidate)
    return subprocess.run([sys.executable, "-c", code, *argv], env=env, capture_output=True, text=True,
                          check=True).stdout.strip()


def main() -> None:
    args = parse_args()
    args.preset = args.preset if args.preset.is_absolute() or args.preset.is_file() else ROOT / args.preset
    args.preset, args.baseline, args.candidate = (path.resolve() for path in (args.preset, args.baseline,
                                                                              args.candidate))
    if args.worker == "shards":
        write_shards(args)
        return
    if args.worker:
        print(json.dumps(evaluate_twice(args)))
        return
    args.frames = args.frames or default_frames(args)
    trees = {"before": args.baseline, "after": args.candidate}
    load = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench_evaluate_") as work:
        args.work = Path(work)
        run_worker(args, "shards", args.candidate)
        runs: dict[str, list[dict]] = {side: [] for side in SIDES}
        for round_index in range(args.rounds):
            for side in SIDES:
                runs[side].append(run_worker(args, side, trees[side], round_index))
                print(f"round {round_index + 1}/{args.rounds} {side}: " + ", ".join(
                    f"{call} {runs[side][-1][call]['fps']:.2f} frames/s (stage {runs[side][-1][call]['stage_fps']:.2f})"
                    for call in CALLS), flush=True)
        same = compare_outputs(*(args.work / f"{side}-{args.rounds - 1}-warm" / "predictions" for side in SIDES))
    after = runs["after"][-1]
    print(f"\n{args.preset.name}: {after['size']} px, {after['frames']} frames ({args.sequences} sequences), batch "
          f"{after['batch']}, precision {after['precision']}, on {after['device']}; loader processes after: "
          f"{after['loader_workers']}; refined path {'on' if args.refine else 'off'}; {args.rounds} rounds, medians")
    print(f"load average (1, 5, 15 min) before the runs: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, after: "
          + " ".join(f"{value:.2f}" for value in os.getloadavg()))
    print("frames/s: the whole call, and the stage's own figure")
    print(f"{'side':8s} {'cold call':>10s} {'cold stage':>11s} {'warm call':>10s} {'warm stage':>11s}  code")
    rates = {side: {(call, key): statistics.median(r[call][key] for r in runs[side])
                    for call in CALLS for key in ("fps", "stage_fps")} for side in SIDES}
    for side in SIDES:
        print(f"{side:8s} " + " ".join(f"{rates[side][call, key]:{width}.2f}" for call in CALLS
                                       for key, width in (("fps", 10), ("stage_fps", 11))) + f"  {trees[side]}")
    print("after / before " + " ".join(f"{rates['after'][call, key] / rates['before'][call, key]:{width}.2f}"
                                       for call in CALLS for key, width in (("fps", 10), ("stage_fps", 11))))
    print(f"outputs of the last call: {same}")


if __name__ == "__main__":
    main()
