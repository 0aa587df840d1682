"""Writing video files: the encoder this PyAV build has, and whole videos of frames (the built-in unlabelled video,
test clips). Reading them is :mod:`endoflow.data.video`'s."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path
from typing import Iterable

import numpy as np

from endoflow.io import atomic_path

# the first one this PyAV build has: H.264, else MPEG-4 part 2
VIDEO_ENCODERS = ("libx264", "libopenh264", "mpeg4")
X264_CRF = "12"  # near-lossless: a video written for training is data, not a preview


def write_video(path: Path, frames: Iterable[np.ndarray], fps: float) -> int:
    """Encode ``frames`` (``H x W x 3`` uint8 RGB, even sizes, all alike) as an mp4 at ``fps``, atomically; returns
    the frame count. One encoder thread: the same frames give the same bytes with the same PyAV build."""
    import av

    encoder = video_encoder()
    count = 0
    with atomic_path(path) as temporary, av.open(str(temporary), mode="w", format="mp4") as container:
        stream = None
        for rgb in frames:
            if stream is None:
                stream = container.add_stream(encoder, rate=Fraction(fps).limit_denominator(1001))
                stream.height, stream.width = rgb.shape[:2]
                stream.pix_fmt = "yuv420p"
                stream.codec_context.thread_count = 1
                if encoder == "libx264":
                    stream.options = {"crf": X264_CRF}
                else:
                    stream.bit_rate = 24 * rgb.shape[0] * rgb.shape[1] * int(fps)
            container.mux(stream.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")))
            count += 1
        if stream is None:
            raise ValueError(f"{path}: no frames to write")
        container.mux(stream.encode(None))
    return count


def video_encoder() -> str:
    """The first of :data:`VIDEO_ENCODERS` this PyAV build encodes with."""
    import av

    for name in VIDEO_ENCODERS:
        try:
            av.codec.Codec(name, "w")
        except av.codec.codec.UnknownCodecError:
            continue
        return name
    raise RuntimeError(f"this PyAV build has none of the video encoders {', '.join(VIDEO_ENCODERS)}")
