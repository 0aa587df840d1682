"""The paper preset through `dvc repro` on this machine's GPU: one short epoch at the paper's step counts.

    python benchmarks/bench_paper_dry_run.py [--bank-steps 200] [--simcol-frames 50] [--out DIR]

The CI dry run (``tests/test_paper_dry_run.py``) cuts every loop to a step so that 2 CPU cores finish it. Here
only the data is cut (synthetic sequences rendered at 480 x 480, ``--simcol-frames`` per SimCol sequence, so one
epoch is short) and ``train.epochs`` is 1: the epoch runs every one of its steps at the paper's batch 12, with
the preset's loader processes, CPUs per worker, GPU and precision; evaluation runs on every test frame. The
latent bank's pretraining is the one loop still cut, to ``--bank-steps`` generator steps per resolution: the
paper's 18,750 (94k in all) take hours. The run's wall time, CPU time and peak memory per stage are printed
(see ``StageMonitor``), with the training and evaluation figures the stages wrote.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import yaml

from endoflow.config import load_params
from tests.test_paper_dry_run import run_paper_dry_run


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bank-steps", type=int, default=200, help="generator steps per resolution")
    parser.add_argument("--simcol-frames", type=int, default=50, help="frames per synthetic SimCol sequence")
    parser.add_argument("--out", type=Path, default=None, help="keep the run here (default: a temporary folder)")
    return parser.parse_args()


def gpu_run_cuts(bank_steps: int, simcol_frames: int) -> dict:
    """The data cut to synthetic 480 x 480 renders, one epoch, and a shortened bank pretraining; nothing else."""
    return {
        "data.simcol.root": "data/raw/synthetic/SimCol3D",
        "data.endoslam.root": "data/raw/synthetic/EndoSLAM",
        "data.scenenet.root": "data/raw/synthetic/SceneNet",
        "synth.size": 480,
        "synth.simcol.sequences": 5,  # S1-S3/B1-B3 train, S4/B4 val, S5/B5 (and O1-O3) test
        "synth.simcol.frames": simcol_frames,
        "synth.endoslam.frames": simcol_frames,
        "synth.scenenet.sequences": 10,
        "latent_bank.steps_per_stage": bank_steps,
        "train.epochs": 1,
    }


def main() -> None:
    args = parse_args()
    with tempfile.TemporaryDirectory(prefix="paper_dry_run_") as tmp:
        clone = args.out or Path(tmp) / "endoflow"
        clone.mkdir(parents=True, exist_ok=True)
        resources = run_paper_dry_run(clone, gpu_run_cuts(args.bank_steps, args.simcol_frames))
        params = load_params(clone / "params.yaml")
        train = json.loads((clone / params.train.metrics).read_text())
        bank = json.loads((clone / params.latent_bank.metrics).read_text())
        evaluation = {name: json.loads((clone / params.eval.metrics / f"{name}.json").read_text())
                      for name in params.eval.test_sets}
    print(yaml.safe_dump({"latent_bank": bank, "train": train}, sort_keys=False)[:6000])
    for name, figures in evaluation.items():
        print(name, figures)
    print("stage          wall s   cpu s  peak RSS GiB (largest process)")
    for stage, figures in resources["stages"].items():
        print(f"{stage:30s} {figures['wall_seconds']:8.1f} {figures['cpu_seconds']:8.1f} "
              f"{figures['peak_rss_gib']:6.2f} ({figures['peak_rss_largest_process_gib']:.2f})")
    print(f"dvc repro: {resources['wall_seconds']:.0f} s wall")


if __name__ == "__main__":
    main()
