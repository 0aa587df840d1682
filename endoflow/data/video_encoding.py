"""Writing video files: the encoder this PyAV build has, and whole videos of frames (the built-in unlabelled video,
test clips). Reading them is :mod:`endoflow.data.video`'s."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path
from typing import Iterable

import numpy as np

from endoflow.io import atomic_path

# for previews (reconstruct's video): the first one this PyAV build has, H.264, else MPEG-4 part 2
VIDEO_ENCODERS = ("libx264", "libopenh264", "mpeg4")
# for data (write_video): MPEG-4 part 2, which gives the same bytes for the same frames in every process (libx264
# does not, even on one thread), at a rate high enough to be near lossless
DATA_ENCODER = "mpeg4"
DATA_BITS_PER_PIXEL = 2.0  # per pixel per frame


def write_video(path: Path, frames: Iterable[np.ndarray], fps: float) -> int:
    """Encode ``frames`` (``H x W x 3`` uint8 RGB, even sizes, all alike) as an mp4 at ``fps`` (MPEG-4 part 2,
    :data:`DATA_ENCODER`), atomically; returns the frame count. The same frames give the same bytes."""
    import av

    count = 0
    with atomic_path(path) as temporary, av.open(str(temporary), mode="w", format="mp4") as container:
        stream = None
        for rgb in frames:
            if stream is None:
                rate = Fraction(fps).limit_denominator(1001)
                stream = container.add_stream(DATA_ENCODER, rate=rate)
                stream.height, stream.width = rgb.shape[:2]
                stream.pix_fmt = "yuv420p"
                stream.codec_context.thread_count = 1
                stream.bit_rate = int(DATA_BITS_PER_PIXEL * rgb.shape[0] * rgb.shape[1] * fps)
            frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
            frame.pts, frame.time_base = count, 1 / rate  # one tick a frame, never guessed
            container.mux(stream.encode(frame))
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
