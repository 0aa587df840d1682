"""DVC stage `synthesize`: procedural data with exact ground truth in the native layouts.

Usage: ``python -m stages.synthesize [--params params.yaml]``; renders with ``data.endoslam``'s depth scale,
pose unit and frame rate, so that the reader decodes what was written. See docs/synthetic_data.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from endoflow.config import load_params
from endoflow.synth.writers import synthesize_layouts

FOLDERS = {"simcol": "SimCol3D", "endoslam": "EndoSLAM", "scenenet": "SceneNet", "video": "Video"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml", help="parameter file (default: params.yaml)")
    args = parser.parse_args()
    params = load_params(args.params)
    outs = {layout: Path(params.synth.out) / folder for layout, folder in FOLDERS.items()}
    print("\n".join(synthesize_layouts(outs, params)), flush=True)


if __name__ == "__main__":
    main()
