"""The ``endoflow`` command line. Each subcommand parses arguments and calls one library function."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Optional, Sequence

from endoflow.config import DATASETS, PRECISIONS, SYNTH_LAYOUTS, ConfigError, load_params
from endoflow.errors import DataFormatError
from endoflow.io import OutputFolderError
from endoflow.sweep import STUDIES

# the exit status of a command ended by Ctrl-C, as a shell reports one killed by SIGINT (128 + 2)
INTERRUPTED = 130

if TYPE_CHECKING:  # the commands import what they run when they run: `endoflow --help` stays quick
    from endoflow.reconstruction.reconstruct import ReconstructOptions


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of the ``endoflow`` console script; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "handler"):
        parser.print_help()
        return 2
    try:
        return int(args.handler(args) or 0)
    except (ConfigError, DataFormatError, FileNotFoundError, OutputFolderError) as exc:
        print(f"endoflow: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        # Ctrl-C is the user's own act: a line, not a traceback. What a command writes is staged and moved into
        # place whole, so the interruption leaves the earlier outputs as they were.
        print("endoflow: interrupted", file=sys.stderr)
        return INTERRUPTED


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser (exposed for tests and documentation)."""
    parser = argparse.ArgumentParser(prog="endoflow", description=__doc__)
    parser.add_argument("--params", default="params.yaml", help="parameter file (default: params.yaml)")
    commands = parser.add_subparsers(title="commands")

    synth = commands.add_parser("synth", help="render procedural data in a dataset's native layout")
    synth.add_argument("--layout", choices=SYNTH_LAYOUTS, required=True)
    synth.add_argument("--out", required=True, type=Path, help="dataset root to create")
    synth.add_argument("--sequences", type=int, default=None)
    synth.add_argument("--frames", type=int, default=None)
    synth.add_argument("--size", type=int, default=None, help="square image size in pixels")
    synth.add_argument("--seed", type=int, default=None)
    synth.set_defaults(handler=_synth)

    data = commands.add_parser("data", help="look at a dataset through our readers").add_subparsers()
    for name, handler, text in (
        ("inspect", _data_inspect, "what the reader understood: sequences, frames, K, depth, poses"),
        ("check", _data_check, "ground-truth consistency: does GT depth + pose explain the motion?"),
    ):
        sub = data.add_parser(name, help=text)
        sub.add_argument("root", type=Path)
        sub.add_argument("--dataset", choices=DATASETS, default=None, help="default: detect from layout")
        sub.add_argument("--json", action="store_true", help="machine-readable output")
        sub.set_defaults(handler=handler)

    model = commands.add_parser("model", help="the depth + pose model").add_subparsers()
    summary = model.add_parser(
        "summary", help="trainable and frozen parameter counts per component, beside the released code's"
    )
    summary.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    summary.add_argument("--json", action="store_true")
    summary.set_defaults(handler=_model_summary)
    export = model.add_parser("export", help="DepthNet and PoseNet as ONNX graphs, checked with onnxruntime")
    export.add_argument("--model", default=None,
                        help="model file, or an MLflow model: models:/<name>/<version> (the store of params.yaml's "
                             "tracking.uri) (default: params' train.out)")
    export.add_argument("--format", choices=["onnx"], default="onnx")
    export.add_argument("--out", type=Path, required=True, help="folder for the graphs and export.json")
    export.set_defaults(handler=_model_export)

    rec = commands.add_parser("reconstruct", help="depth, camera path and fused surface of a video, an image "
                                                  "folder or a dataset sequence, from a trained model; of many "
                                                  "videos as Ray tasks")
    rec.add_argument("input", type=Path, nargs="+",
                     help="video file, folder of images, or dataset root (with --sequence); or several videos and "
                          "folders of videos: one Ray task each (on params.yaml's ray.address, else a local Ray), "
                          "one folder each under --out, a rerun keeping those done with the same settings")
    rec.add_argument("--model", default="models/endoflow.pt",
                     help="model file of the train stage, or an MLflow model: models:/<name>/<version> (the store "
                          "of params.yaml's tracking.uri)")
    rec.add_argument("--out", type=Path, required=True,
                     help="output folder: new, empty or an earlier reconstruction (replaced when the run completes); "
                          "for many videos the folder of their folders, each named after its video")
    rec.add_argument("--force", action="store_true",
                     help="replace --out even if it holds other files (never when it is or holds the input or model)")
    rec.add_argument("--sequence", default=None, help="a sequence of the dataset at INPUT (ground truth comes along)")
    rec.add_argument("--pattern", default=None, metavar="GLOB",
                     help="the frames of a folder INPUT, e.g. '*_color.png' (default: every image; a folder mixing "
                          "frames with other images, such as depth maps, is refused)")
    rec.add_argument("--intrinsics", default=None,
                     help="cam.txt, YAML/JSON with fx, fy, cx, cy, width, height, or fx,fy,cx,cy in pixels of "
                          "the input frames (a dataset sequence brings its own; without: the intrinsics the model "
                          "learned for video, else a centred pinhole of data.assumed_fov_deg, as it prints)")
    rec.add_argument("--size", type=int, default=None, help="square model input in px (default: the model's)")
    rec.add_argument("--crop", default=None, metavar="X,Y,W,H",
                     help="use this region of the frames (pixels; e.g. one half of a side-by-side frame); the model "
                          "sees its centre square (default: the centre square of the whole frame)")
    rec.add_argument("--start", type=int, default=0, help="first frame (position in the input)")
    rec.add_argument("--stop", type=int, default=None, help="stop before this frame")
    rec.add_argument("--stride", type=int, default=1, help="use every K-th frame")
    rec.add_argument("--scale", type=float, default=1.0,
                     help="known factor on depth and path (e.g. from an instrument of known size)")
    rec.add_argument("--voxel-cm", type=float, default=None, help="TSDF voxel edge in cm (default: from K and depth)")
    rec.add_argument("--trunc-cm", type=float, default=None, help="TSDF truncation in cm (default: 4 voxels)")
    rec.add_argument("--npy", action="store_true", help="also write float32 depth in cm as .npy")
    rec.add_argument("--no-fusion", dest="fuse", action="store_false", help="skip the TSDF surface")
    rec.add_argument("--no-refine", dest="refine", action="store_false",
                     help="keep the pose network's path as it is (default: refined by photometric alignment to "
                          "keyframes with the predicted depth, as params.yaml's refine section says)")
    rec.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    rec.add_argument("--precision", choices=PRECISIONS, default=None,
                     help="the networks' arithmetic: float32 (the same outputs on any machine), bf16 (faster networks "
                          "on a CPU or GPU with bf16 arithmetic, depth and path a little different: "
                          "docs/reconstruction.md, 'Precision') or auto (bf16 on a GPU that has it; default: "
                          "params.yaml's reconstruct.precision)")
    rec.add_argument("--threads", type=_positive_int, default=None,
                     help="torch's CPU threads (default: the model's params' threads; a fixed count gives the "
                          "same depth on any machine, another count sums in another order)")
    rec.add_argument("--mlflow", action="store_true",
                     help="log the pictures, path, surface and summary into the model's MLflow run (the store of "
                          "params.yaml's tracking.uri; a new run, with a warning, if the store lacks it)")
    rec.set_defaults(handler=_reconstruct)

    rec.add_argument("--adapt", type=int, default=0, metavar="STEPS",
                     help="first fit the model to the input with `endoflow adapt` for this many steps (0: not); "
                          "where the fit explains its held-out frames better, the fitted model reconstructs and is "
                          "written into --out as model_adapted.pt (with --mlflow the fit is logged, kept or not)")

    fit = commands.add_parser("adapt", help="fit a trained model to one video (self-supervised fine-tuning), "
                                            "measured on held-out frames")
    fit.add_argument("input", type=Path, help="video file, folder of images, or dataset root (with --sequence)")
    fit.add_argument("--model", default="models/endoflow.pt", help="model file, or models:/<name>/<version>")
    fit.add_argument("--out", type=Path, required=True, help="the adapted model file to write")
    fit.add_argument("--steps", type=_positive_int, default=None, help="optimiser steps (default: 300)")
    fit.add_argument("--sequence", default=None, help="a sequence of the dataset at INPUT (its ground truth unused)")
    fit.add_argument("--pattern", default=None, metavar="GLOB", help="as reconstruct's: the frames of a folder INPUT")
    fit.add_argument("--intrinsics", default=None,
                     help="as reconstruct's; without: learned on the video, from the model's video camera or the "
                          "assumed pinhole")
    fit.add_argument("--crop", default=None, metavar="X,Y,W,H", help="use this region of the frames (pixels)")
    fit.add_argument("--start", type=int, default=0, help="first frame (position in the input)")
    fit.add_argument("--stop", type=int, default=None, help="stop before this frame")
    fit.add_argument("--stride", type=int, default=1, help="use every K-th frame")
    fit.add_argument("--held-out", type=float, default=None,
                     help="the last share of the frames, never trained on, that measures the fit (default: 0.2)")
    fit.add_argument("--lr", type=float, default=None,
                     help="learning rate (default: a tenth of the model's train.lr)")
    fit.add_argument("--batch-size", type=_positive_int, default=None,
                     help="triplets per step (default: the model's train.batch_size)")
    fit.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    fit.add_argument("--threads", type=_positive_int, default=None,
                     help="torch's CPU threads (default: the model's params' threads)")
    fit.add_argument("--no-mlflow", dest="mlflow", action="store_false",
                     help="do not log a run and an MLflow model (default: both, in params.yaml's tracking store)")
    fit.set_defaults(handler=_adapt)

    report = commands.add_parser("report", help="Markdown tables (paper Tables 1-3) of workspace + DVC experiments")
    report.add_argument("--no-experiments", action="store_true", help="only the workspace's metrics")
    report.add_argument("--all-commits", action="store_true",
                        help="the experiments of every commit, not only HEAD's (a sweep queued before a commit)")
    report.set_defaults(handler=_report)

    sweep = commands.add_parser("sweep", help="queue a study's configurations x seeds as DVC experiments and run "
                                              "them (the paper's Table 3, the VAE, motion or mask study, with "
                                              "seed statistics)")
    sweep.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds (default: 0 1 2)")
    sweep.add_argument("--study", choices=STUDIES, default="ablation",
                       help="ablation: the four configurations (default); vae: the full model without the warp's "
                            "sampling and with beta over decades (docs/method.md, 'What the VAE contributes'); "
                            "motion: with mixed frame offsets, the depth consistency, both; mask: without "
                            "auto-masking and with it for the pose alone (docs/results.md)")
    sweep.add_argument("--no-start", dest="start", action="store_false",
                       help="only queue them (start later with `dvc queue start -j 1`)")
    sweep.set_defaults(handler=_sweep)

    params = commands.add_parser("params", help="write the full, documented params file DVC reads: the defaults, "
                                                "or a preset's differences over them")
    params.add_argument("--preset", type=Path, default=None, help="a preset (presets/paper.yaml); default: none")
    params.add_argument("--out", type=Path, default=None, help="file to write (params.yaml); default: print it")
    params.set_defaults(handler=_params)
    return parser


def _print(result: Any, as_json: bool, text: str) -> None:
    print(json.dumps(result, indent=2, default=_json_default) if as_json else text)


def _json_default(value: Any) -> Any:
    if hasattr(value, "tolist"):
        return value.tolist()
    return str(value)


def _synth(args: argparse.Namespace) -> int:
    from endoflow.synth.writers import synthesize_layout

    summary = synthesize_layout(
        args.layout,
        args.out,
        sequences=args.sequences,
        frames=args.frames,
        size=args.size,
        seed=args.seed,
        params=_params_if_present(args.params),
    )
    print(summary)
    return 0


def _data_inspect(args: argparse.Namespace) -> int:
    from endoflow.data.inspect import format_inspection, inspect_dataset

    params = _params_if_present(args.params)
    report = inspect_dataset(args.root, args.dataset, params)
    _print(report, args.json, format_inspection(report))
    return 0


def _data_check(args: argparse.Namespace) -> int:
    from endoflow.data.check import check_dataset, format_check

    params = _params_if_present(args.params)
    report = check_dataset(args.root, args.dataset, params)
    _print(report, args.json, format_check(report))
    return 0 if report["ok"] else 1


def _model_summary(args: argparse.Namespace) -> int:
    from endoflow.models.summary import format_summary, model_summary

    params = load_params(args.params, overrides=args.overrides)
    report = model_summary(params)
    _print(report, args.json, format_summary(report))
    return 0


def _adapt(args: argparse.Namespace) -> int:
    from endoflow.devices import use_cpu_threads
    from endoflow.models.model_file import load_model_file
    from endoflow.training.adapt import AdaptOptions

    given = {"steps": args.steps, "held_out": args.held_out}  # left out: AdaptOptions' defaults
    try:
        options = AdaptOptions(lr=args.lr, batch_size=args.batch_size, start=args.start, stop=args.stop,
                               stride=args.stride, device=args.device,
                               **{key: value for key, value in given.items() if value is not None})
    except ValueError as exc:
        print(f"endoflow adapt: error: {exc}", file=sys.stderr)
        return 2
    with _model_file(args.model, args.params) as model_path:
        use_cpu_threads(args.threads or load_model_file(model_path).params.threads)
        _run_adaptation(args, model_path, args.out, options)
    return 0


def _run_adaptation(args: argparse.Namespace, model_path: Path, out: Path, options: Any) -> dict:
    """``endoflow adapt`` of ``args.input`` (also ``reconstruct --adapt``), in an MLflow run unless ``--no-mlflow``."""
    from endoflow.data.crop import Crop
    from endoflow.models.model_file import load_model_file
    from endoflow.training.adapt import adapt, input_sequence, log_adaptation

    record = load_model_file(model_path)
    crop = Crop.parse(args.crop) if args.crop else None
    sequence = input_sequence(args.input, args.sequence, record.params, crop, args.intrinsics, args.pattern)
    if not args.mlflow:
        return adapt(sequence, model_path, out, options)
    from endoflow import tracking

    tracking_params = _params_if_present(args.params)
    with tracking.run(tracking_params, Path(".").resolve(), tracking_params.tracking.experiment,
                      f"adapt {sequence.name}") as run:
        summary = adapt(sequence, model_path, out, options, run)
        log_adaptation(run, summary, out)
    return summary


def _reconstruct(args: argparse.Namespace) -> int:
    from endoflow.reconstruction.many import holds_videos

    try:
        options = _reconstruct_options(args)
    except ValueError as exc:
        print(f"endoflow reconstruct: error: {exc}", file=sys.stderr)
        return 2
    # a dataset root with --sequence, or a folder whose images --pattern picks, is one input even if it holds videos
    one_input = args.sequence is not None or args.pattern is not None
    if len(args.input) > 1 or (not one_input and holds_videos(args.input[0])):
        return _reconstruct_many(args, options)
    # from here on one input, as `endoflow adapt` (run first for --adapt) takes it
    return _reconstruct_one(argparse.Namespace(**{**vars(args), "input": args.input[0]}), options)


def _reconstruct_options(args: argparse.Namespace) -> ReconstructOptions:
    """``ReconstructOptions`` of the arguments (and params.yaml's refine section and reconstruct.precision); a
    ValueError says what is wrong."""
    from endoflow.data.crop import Crop
    from endoflow.geometry.direct_alignment import tracker_settings
    from endoflow.reconstruction.frames import FrameRange
    from endoflow.reconstruction.reconstruct import ReconstructOptions

    params = _params_if_present(args.params)
    return ReconstructOptions(FrameRange(args.start, args.stop, args.stride), args.size, args.scale,
                              args.voxel_cm, args.trunc_cm, args.npy, args.fuse, args.device, args.force,
                              Crop.parse(args.crop) if args.crop else None,
                              tracker_settings(params.refine) if args.refine and params.refine.enabled else None,
                              args.precision or params.reconstruct.precision)


def _reconstruct_many(args: argparse.Namespace, options: ReconstructOptions) -> int:
    """Several videos, one Ray task and one folder under ``--out`` each; 1 when a video failed (the others'
    folders are written)."""
    from endoflow.models.model_file import load_model_file
    from endoflow.reconstruction.many import ManySettings, format_outcome, reconstruct_videos, video_files

    for given, option in ((args.sequence, "--sequence"), (args.pattern, "--pattern"), (args.adapt, "--adapt"),
                          (args.mlflow, "--mlflow")):
        if given:
            print(f"endoflow reconstruct: error: {option} takes one input; reconstruct the videos that need it one "
                  f"at a time", file=sys.stderr)
            return 2
    videos = video_files(args.input)
    with _model_file(args.model, args.params) as model_path:
        threads = args.threads or load_model_file(model_path).params.threads
        outcome = reconstruct_videos(videos, args.out, ManySettings(model_path, args.intrinsics, options, threads),
                                     _params_if_present(args.params).ray)
    print(format_outcome(outcome))
    if outcome.failed:
        print(f"endoflow reconstruct: error: {len(outcome.failed)} of {outcome.total} videos failed (named above; "
              f"their folders are as they were); rerun the command to retry them, the others are kept",
              file=sys.stderr)
        return 1
    return 0


def _reconstruct_one(args: argparse.Namespace, options: ReconstructOptions) -> int:
    from endoflow.devices import use_cpu_threads
    from endoflow.models.model_file import load_model_file
    from endoflow.reconstruction.frames import intrinsics_for, open_frames
    from endoflow.reconstruction.reconstruct import (ADAPTED_MODEL, Adaptation, check_output_folder,
                                                     log_reconstruction, reconstruct)
    from endoflow.training.adapt import AdaptOptions, fits_better

    with _model_file(args.model, args.params) as model_path, tempfile.TemporaryDirectory() as scratch:
        record = load_model_file(model_path)
        use_cpu_threads(args.threads or record.params.threads)
        frames = open_frames(args.input, args.sequence, record.params, args.pattern)
        K = intrinsics_for(args.intrinsics, frames, options.crop)
        adaptation = None
        if args.adapt:
            check_output_folder(args.out, frames, model_path, options.force)  # before the fit's minutes
            adapted = Path(scratch) / ADAPTED_MODEL
            fit = _run_adaptation(args, model_path, adapted, AdaptOptions(
                steps=args.adapt, start=args.start, stop=args.stop, stride=args.stride, device=args.device))
            adaptation = Adaptation.of(adapted, fit, fits_better(fit))
        summary = reconstruct(frames, K, model_path, args.out, options, adaptation=adaptation)
    if args.mlflow:
        run = log_reconstruction(_params_if_present(args.params), Path(".").resolve(), record.mlflow_run_id,
                                 args.out.name, args.out)
        print(f"logged to MLflow run {run.run_id} under reconstruct/{args.out.name}/")
    scale = summary.get("ground_truth_scale")
    fitted = f"; ground truth fits the model's depth x {scale['median']:.3f}" if scale else ""
    print(f"{summary['frames']} frames at {summary['size']} px, {summary['frames_per_second']:.1f} frames/s"
          f"{fitted}; outputs in {args.out}")
    return 0


@contextlib.contextmanager
def _model_file(location: str, params_path: str) -> Iterator[Path]:
    """A model file, or an MLflow model's (downloaded from the store of ``tracking.uri`` for the duration)."""
    from endoflow.models.mlflow_model import is_model_uri, local_model_file

    if not is_model_uri(location):
        yield Path(location)
        return
    from endoflow import tracking  # MLflow takes seconds to import: only model URIs pay for it

    with local_model_file(location, tracking.tracking_uri(_params_if_present(params_path), ".")) as path:
        yield path


def _model_export(args: argparse.Namespace) -> int:
    from endoflow.models.export import ExportVerificationError, export_onnx, format_export

    location = args.model or _params_if_present(args.params).train.out
    with _model_file(location, args.params) as model_path:
        try:
            report = export_onnx(model_path, args.out, model_label=location)
        except ExportVerificationError as exc:  # the graphs are not trustworthy: nothing was replaced
            print(f"endoflow: error: {exc}", file=sys.stderr)
            return 1
    print(format_export(report))
    return 0


def _report(args: argparse.Namespace) -> int:
    from endoflow.config import params_to_dict
    from endoflow.report import build_report

    params = _params_if_present(args.params)
    print(build_report(".", params.eval.predictions, params_to_dict(params), experiments=not args.no_experiments,
                       all_commits=args.all_commits),
          end="")
    return 0


def _sweep(args: argparse.Namespace) -> int:
    from endoflow.sweep import SweepError, run_sweep

    try:
        run_sweep(".", args.seeds, start=args.start, study=args.study)
    except SweepError as exc:
        print(f"endoflow sweep: error: {exc}", file=sys.stderr)
        return 1
    return 0


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text}")
    return value


def _params_if_present(path: str):
    """Data commands work outside a project too: without params.yaml they use the defaults."""
    from endoflow.config import Params

    return load_params(path) if Path(path).is_file() else Params()


def _params(args: argparse.Namespace) -> int:
    from endoflow.params_file import preset_yaml, write_params_file

    if args.out is None:
        print(preset_yaml(args.preset), end="")
        return 0
    write_params_file(args.out, args.preset)
    print(f"wrote {args.out}: the defaults" + (f" with {args.preset}" if args.preset else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
