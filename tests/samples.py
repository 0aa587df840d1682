"""Where the real sample files live: ``../shared/samples`` beside the repository (as in CI)."""

from pathlib import Path

SIMCOL_SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "samples" / "simcol3d"
C3VD_SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "samples" / "c3vd"
COLONOSCOPY_CLIP = Path(__file__).resolve().parents[2] / "shared" / "samples" / "colonoscopy_video" / "colonoscopy.mp4"
