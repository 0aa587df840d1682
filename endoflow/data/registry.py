"""Open a dataset root with the right reader, named or detected from the folder layout."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional

from endoflow.config import Params
from endoflow.data.base import DATASETS, DatasetReader
from endoflow.data.c3vd import POSE_FILE as C3VD_POSE_FILE
from endoflow.data.c3vd import C3VDReader
from endoflow.data.endoslam import EndoSLAMReader
from endoflow.data.scenenet import SPLITS as SCENENET_SPLITS
from endoflow.data.scenenet import SceneNetReader
from endoflow.data.simcol import SCENES as SIMCOL_SCENES
from endoflow.data.simcol import SimColReader
from endoflow.data.video import IMAGE_SUFFIXES, VIDEO_SUFFIXES, VideoReader
from endoflow.errors import DataFormatError


def _looks_like_simcol(root: Path) -> bool:
    return any((root / scene).is_dir() for scene in SIMCOL_SCENES)


def _looks_like_endoslam(root: Path) -> bool:
    return (root / "UnityCam").is_dir() or (root / "Cameras").is_dir()


def _looks_like_scenenet(root: Path) -> bool:
    # A bare train/ folder is common; SceneNet's has <part>/<trajectory>/depth/ below it.
    return any(any((root / split).glob("*/*/depth")) for split in SCENENET_SPLITS if (root / split).is_dir())


def _looks_like_c3vd(root: Path) -> bool:
    return any(any(folder.glob("*_color.png")) for folder in (p.parent for p in root.glob(f"*/{C3VD_POSE_FILE}")))


def _looks_like_video(root: Path) -> bool:
    # frame folders without C3VD's pose file beside their images
    return any((p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)
               or (p.is_dir() and not (p / C3VD_POSE_FILE).exists() and _holds_images(p)) for p in root.iterdir())


def _holds_images(folder: Path) -> bool:
    return any(p.suffix.lower() in IMAGE_SUFFIXES for p in folder.iterdir())


LAYOUT_TESTS: dict[str, Callable[[Path], bool]] = {
    "simcol": _looks_like_simcol,
    "endoslam": _looks_like_endoslam,
    "scenenet": _looks_like_scenenet,
    "c3vd": _looks_like_c3vd,
    "video": _looks_like_video,
}

EXPECTED_LAYOUTS = (
    "simcol: SyntheticColon_I/, SyntheticColon_II/ or SyntheticColon_III/; "
    "endoslam: UnityCam/ or Cameras/; "
    "scenenet: train/ or val/ holding <part>/<trajectory>/depth/; "
    "c3vd: sequence folders holding pose.txt and <n>_color.png; "
    "video: video files or folders of images"
)


def detect_dataset(root: str | Path) -> str:
    """The dataset whose native layout ``root`` has.

    Raises:
        DataFormatError: no layout matches, or more than one does (then pass the dataset name).
    """
    root = Path(root)
    if not root.is_dir():
        raise DataFormatError(root, "dataset root folder not found")
    matches = [name for name, looks_like in LAYOUT_TESTS.items() if looks_like(root)]
    if not matches:
        raise DataFormatError(root, f"no known dataset layout found; expected one of: {EXPECTED_LAYOUTS}")
    if len(matches) > 1:
        raise DataFormatError(root, f"layout matches several datasets ({', '.join(matches)}); name one with --dataset")
    return matches[0]


def open_reader(root: str | Path, dataset: Optional[str], params: Params) -> DatasetReader:
    """The reader for ``root``; ``dataset`` None detects it from the layout. Settings: ``params.data.<name>``.

    Raises:
        DataFormatError: unknown dataset name, missing root, or no recognisable layout.
    """
    name = dataset if dataset is not None else detect_dataset(root)
    if name == "simcol":
        return SimColReader(root, params.data.simcol)
    if name == "endoslam":
        return EndoSLAMReader(root, params.data.endoslam)
    if name == "scenenet":
        return SceneNetReader(root, params.data.scenenet)
    if name == "c3vd":
        return C3VDReader(root, params.data.c3vd)
    if name == "video":
        return VideoReader(root, params.data.video, params.data.assumed_fov_deg)
    raise DataFormatError(root, f"unknown dataset {name!r} (known: {', '.join(DATASETS)})")
