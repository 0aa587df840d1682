"""The error every reader raises keeps its file and problem across processes."""

import pickle
from pathlib import Path

from endoflow.errors import DataFormatError


def test_data_format_error_names_file_and_problem():
    error = DataFormatError(Path("/x/Depth_0001.png"), "expected 16-bit depth, found uint8")
    assert str(error) == "/x/Depth_0001.png: expected 16-bit depth, found uint8"


def test_data_format_error_survives_pickling_from_worker_processes():
    error = pickle.loads(pickle.dumps(DataFormatError("/x/cam.txt", "malformed cam.txt")))
    assert isinstance(error, DataFormatError)
    assert (error.path, error.problem) == (Path("/x/cam.txt"), "malformed cam.txt")
    assert str(error) == "/x/cam.txt: malformed cam.txt"
