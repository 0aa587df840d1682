"""A reconstruction as a Rerun recording, ``recording.rrd``: what the SLAM and visual-odometry community opens
such outputs in. Open it with the viewer of the version pinned in ``pyproject.toml`` (a recording opens in the
same or the next minor version only): ``rerun recording.rrd`` (see ``docs/reconstruction.md``).

Entities, in the first camera's frame (OpenCV: x right, y down, z forward; cm), on the timeline ``frame`` (each
frame's position in the input):

- ``world/camera``: the camera-to-world pose ``T_world_cam`` and a pinhole with K at the model's input size;
- ``world/camera/image`` the frame as the model saw it (JPEG), ``world/camera/depth`` its z-depth (16-bit counts
  of the depth PNGs' unit, declared to the viewer so that it unprojects them in cm);
- ``world/path`` the camera path; ``world/ground_truth_path`` the input's own, where it has one, mapped into
  the path's world as the measurement aligns them
  (:func:`~endoflow.reconstruction.alignment.ground_truth_in_path_world`);
- ``world/surface`` the fused mesh, with its vertex colours.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from endoflow.data.frame_encoding import depth_to_counts
from endoflow.reconstruction.fusion import SurfaceMesh

RECORDING_FILE = "recording.rrd"
APPLICATION = "endoflow"
PATH_COLOUR = (255, 140, 0)
GROUND_TRUTH_COLOUR = (40, 200, 40)
JPEG_QUALITY = 90  # a recording of raw frames would be several times the size of the whole output folder


class Recording:
    """Writes ``path`` as frames come (:meth:`add_frame`) and the whole path and surface at the end
    (:meth:`finish`)."""

    def __init__(self, path: Path, name: str) -> None:
        import rerun as rr  # only a reconstruction pays for its import

        self.rr = rr
        self.stream = rr.RecordingStream(APPLICATION)
        self.stream.save(path)
        self.stream.send_recording_name(name)
        self.stream.log("world", rr.ViewCoordinates.RDF, static=True)  # OpenCV's camera axes, in the first camera

    def add_frame(self, index: int, rgb: np.ndarray, depth_cm: np.ndarray, unit_cm: float, K: np.ndarray,
                  T_world_cam: np.ndarray) -> None:
        """One frame at its input position ``index``: the model's input image, its depth (stored in counts of
        ``unit_cm``) and the posed camera."""
        rr = self.rr
        self.stream.set_time("frame", sequence=index)
        self.stream.log("world/camera", rr.Transform3D(translation=T_world_cam[:3, 3], mat3x3=T_world_cam[:3, :3]))
        height, width = depth_cm.shape
        self.stream.log("world/camera", rr.Pinhole(image_from_camera=K, width=width, height=height,
                                                   camera_xyz=rr.ViewCoordinates.RDF))
        self.stream.log("world/camera/image", rr.Image(rgb).compress(jpeg_quality=JPEG_QUALITY))
        counts, _ = depth_to_counts(depth_cm, unit_cm)
        self.stream.log("world/camera/depth", rr.DepthImage(counts, meter=1.0 / unit_cm))  # counts per world unit (cm)

    def finish(self, poses: np.ndarray, ground_truth: Optional[np.ndarray], mesh: Optional[SurfaceMesh]) -> None:
        """The camera path (``N x 4 x 4``), the ground-truth positions in its world (``N x 3``, or None) and the
        fused surface (None: fusion was off), then the file is closed."""
        rr = self.rr
        self.stream.log("world/path", rr.LineStrips3D([poses[:, :3, 3]], colors=[PATH_COLOUR]), static=True)
        if ground_truth is not None:
            self.stream.log("world/ground_truth_path", rr.LineStrips3D([ground_truth], colors=[GROUND_TRUTH_COLOUR]),
                            static=True)
        if mesh is not None and len(mesh.triangles):
            self.stream.log("world/surface", rr.Mesh3D(vertex_positions=mesh.vertices, triangle_indices=mesh.triangles,
                                                       vertex_colors=mesh.colours), static=True)
        self.stream.flush()
        self.stream.disconnect()
