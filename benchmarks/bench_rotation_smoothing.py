"""How much of the refined path's rotation error is frame-to-frame jitter: a test set's refined path (what `evaluate`
scores as ``refined``) with its orientations smoothed at several widths, beside constant velocity and the truth
smoothed alike (what smoothing costs a path that is right).

    python benchmarks/bench_rotation_smoothing.py [--params params.yaml] [--test-set simcol_12 | --split val]
                                                  [--sigmas 0 1 2 3 5 8] [--priors 0.1] [--threads 2]

The evaluation's own reader and tracker (``SequenceEvaluator``, the model of ``eval.model``, the settings of
``refine``) run once per rotation prior in ``--priors``; each width in ``--sigmas`` (frames,
:mod:`endoflow.geometry.path_smoothing`) smooths the same aligned path as the evaluation does
(``evaluate.refined_path``). ``--split val`` takes every SimCol3D
sequence of that split (what ``refine.rotation_smoothing`` was chosen on), ``--test-set`` one of ``eval.test_sets``.
Printed per prior and width, averaged over the sequences as the evaluation averages them: the challenge's RTE (cm)
and ROT (deg). A diagnosis, not a speed figure.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

from endoflow.config import ConfigError, EvalSetConfig, Params, load_params
from endoflow.devices import resolve_device, to_compute_layout, use_cpu_threads
from endoflow.evaluation import evaluate, metrics
from endoflow.evaluation.baselines import baseline_relative_poses
from endoflow.geometry.direct_alignment import tracker_settings
from endoflow.geometry.path_smoothing import smooth_path_orientations
from endoflow.models.endoflow_model import load_trained_model


def tracked_sequences(params: Params, test_set: EvalSetConfig, prior: float) -> tuple[list, object]:
    """Each sequence's result and its longest posed run, and the model's training baselines."""
    urls = evaluate.eval_set_shards(params.eval.shards, test_set)
    device = resolve_device(params.eval.device, "eval.device")
    model, record = load_trained_model(params.eval.model, device)
    model = to_compute_layout(model, device, params.eval.precision, params.data.size)
    refine = tracker_settings(params.refine.replace(rotation_prior=prior))
    with tempfile.TemporaryDirectory() as scratch:
        evaluator = evaluate.SequenceEvaluator(model, record.baselines, Path(scratch), device, params.eval.precision,
                                               0, refine)
        evaluate.record_test_set(evaluator, params, test_set, urls, 0, False)
    runs = [(seq, run) for seq in evaluator.sequences
            if (run := evaluate.longest_posed_run(seq.poses, seq.gaps)) is not None]
    return runs, record.baselines


def figures(runs: list, relative_of) -> tuple[float, float]:
    """Mean over sequences of the challenge's RTE and ROT of the relative poses ``relative_of(seq, start, stop, gt)``
    over each sequence's longest posed run ``[start, stop)`` (``gt`` its GT poses)."""
    scores = []
    for seq, (start, stop) in runs:
        gt = np.stack(seq.poses[start:stop])
        scores.append(metrics.simcol_pose_sequence(gt, relative_of(seq, start, stop, gt)))
    return float(np.mean([s["rte"] for s in scores])), float(np.mean([s["rot"] for s in scores]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--params", type=Path, default=Path("params.yaml"))
    choice = parser.add_mutually_exclusive_group()
    choice.add_argument("--test-set", default="simcol_12", help="one of the params' eval.test_sets")
    choice.add_argument("--split", choices=["val", "test"], help="every SimCol3D sequence of this split instead")
    parser.add_argument("--sigmas", type=float, nargs="+", default=[0, 1, 2, 3, 5, 8])
    parser.add_argument("--priors", type=float, nargs="+", default=None,
                        help="refine.rotation_prior values to track with (default: the params')")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    if not all(0 <= value < float("inf") for value in [*args.sigmas, *(args.priors or [])]):
        parser.error(f"--sigmas {args.sigmas} and --priors {args.priors}: each must be finite and >= 0")
    try:
        params = load_params(args.params)
    except ConfigError as error:
        parser.error(str(error))
    if args.split is not None:
        test_set, name = EvalSetConfig(dataset="simcol", split=args.split), f"SimCol3D {args.split}"
    elif args.test_set in params.eval.test_sets:
        test_set, name = params.eval.test_sets[args.test_set], args.test_set
    else:
        parser.error(f"--test-set {args.test_set}: not one of the params' test sets "
                     f"({', '.join(params.eval.test_sets)})")
    if not Path(params.eval.model).is_file():
        parser.error(f"eval.model {params.eval.model}: no such model file (run `dvc repro train` first)")
    use_cpu_threads(args.threads)
    torch.manual_seed(0)
    priors = args.priors if args.priors is not None else [params.refine.rotation_prior]
    print(f"{name}: refined path, RTE (cm) / ROT (deg), mean over sequences")
    print("| rotation prior | " + " | ".join(f"sigma {s:g}" for s in args.sigmas) + " |")
    print("| --- " * (len(args.sigmas) + 1) + "|")
    for prior in priors:
        runs, baselines = tracked_sequences(params, test_set, prior)
        cells = [figures(runs, lambda seq, start, stop, gt, s=s:
                         metrics.relative_poses(evaluate.refined_path(seq, s)[start:stop])) for s in args.sigmas]
        print(f"| {prior:g} | " + " | ".join(f"{rte:.4f} / {rot:.3f}" for rte, rot in cells) + " |")
    truth = [figures(runs, lambda seq, start, stop, gt, s=s: metrics.relative_poses(smooth_path_orientations(gt, s)))
             for s in args.sigmas]
    print("| the truth smoothed | " + " | ".join(f"{rte:.4f} / {rot:.3f}" for rte, rot in truth) + " |")
    constant = figures(runs, lambda seq, start, stop, gt:
                       baseline_relative_poses(baselines, len(gt) - 1)["constant_velocity"])
    print(f"constant velocity: {constant[0]:.4f} / {constant[1]:.3f}; {len(runs)} sequences")


if __name__ == "__main__":
    main()
