"""Frames of a video file, decoded with PyAV (which ships its own FFmpeg).

`video_frames(path, every=N | fps=F, max_frames=M)` decodes the stream once and keeps
every N-th frame, or frames F times a second (by their timestamps), then at most M of
them evenly spaced. Each frame is named by its timestamp, `<video stem>_<seconds>s`
with millisecond precision (`clip_00012.345s`), so outputs say where in the video they
come from and sort in time order. The EXIF-like display rotation of phone videos is
applied when PyAV reports it.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
from PIL import Image

__all__ = ["VIDEO_EXTENSIONS", "VideoError", "VideoFrame", "DEFAULT_FPS", "frame_name", "is_video", "video_frames"]

VIDEO_EXTENSIONS = (".mp4", ".mov", ".m4v", ".mkv", ".avi", ".webm", ".mpg", ".mpeg", ".wmv", ".flv", ".3gp")
DEFAULT_FPS = 1.0
"""Frames per second kept when neither `every` nor `fps` is given (upstream's demo: 1)."""


class VideoError(ValueError):
    """A video that cannot be opened or decoded (the message names the file)."""


@dataclasses.dataclass
class VideoFrame:
    """One kept frame: its name (by timestamp), time in seconds and RGB image."""

    name: str
    time: float
    image: Image.Image


def is_video(path: str | os.PathLike) -> bool:
    p = Path(path)
    return p.is_file() and p.suffix.lower() in VIDEO_EXTENSIONS


def frame_name(stem: str, seconds: float) -> str:
    """`<stem>_<seconds, 5 digits . 3 digits>s`: sorts in time order up to 27 hours."""
    return f"{stem}_{seconds:09.3f}s"


def _evenly(items: list, m: int | None) -> list:
    if m is None or len(items) <= m:
        return items
    if m == 1:
        return items[:1]
    idx = sorted({round(i * (len(items) - 1) / (m - 1)) for i in range(m)})
    return [items[i] for i in idx]


def _decoded(path: Path) -> Iterator[tuple[float, "object"]]:
    import av

    try:
        container = av.open(str(path))
    except Exception as e:  # av.error.* (InvalidDataError, FileNotFoundError, ...)
        raise VideoError(f"cannot open video {path}: {type(e).__name__}: {e}") from None
    with container:
        if not container.streams.video:
            raise VideoError(f"{path} has no video stream")
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"  # frame-parallel decoding
        base = stream.time_base
        start = stream.start_time or 0
        n = 0
        try:
            for frame in container.decode(stream):
                pts = frame.pts if frame.pts is not None else n
                t = float((pts - start) * base) if base is not None else n / float(stream.average_rate or 30)
                n += 1
                yield max(t, 0.0), frame
        except Exception as e:  # noqa: BLE001 - a decode error mid-stream
            if n == 0:
                raise VideoError(f"cannot decode video {path}: {type(e).__name__}: {e}") from None
            # frames before a damaged tail are still usable; the caller sees fewer frames


def _upright(frame) -> Image.Image:
    """The frame as a PIL image, turned by the stream's display rotation (phones store
    portrait video as landscape plus a rotation), as players show it."""
    img = frame.to_image()
    rot = getattr(frame, "rotation", 0) or 0  # degrees counter-clockwise (PyAV >= 14)
    if rot % 360:
        img = img.rotate(rot % 360, expand=True)
    return img


def video_frames(path: str | os.PathLike, *, every: int | None = None, fps: float | None = None,
                 max_frames: int | None = None, warn: Callable[[str], None] | None = None) -> list[VideoFrame]:
    """Frames of `path` as RGB PIL images, in time order.

    every: keep frames 0, N, 2N, ... of the decoded stream; fps: keep the first frame at
    or after each multiple of 1/F seconds; neither: `fps=DEFAULT_FPS`. max_frames: then
    at most M of the kept frames, evenly spaced (first and last included). Raises
    VideoError (file named) when nothing can be decoded."""
    path = Path(path)
    if every is not None and fps is not None:
        raise ValueError("give either every (frames) or fps (frames per second), not both")
    if every is not None and every < 1:
        raise ValueError(f"every must be at least 1; got {every}")
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number; got {fps}")
    if every is None and fps is None:
        fps = DEFAULT_FPS
    kept: list[tuple[float, object]] = []
    next_t = 0.0
    total = 0
    for i, (t, frame) in enumerate(_decoded(path)):
        total += 1
        if every is not None:
            take = i % every == 0
        else:
            take = t + 1e-6 >= next_t
            if take:
                next_t = (np.floor(t * fps + 1e-6) + 1) / fps
        if take:
            # convert now: frames are reused by the decoder
            kept.append((t, _upright(frame)))
            if max_frames is not None and len(kept) > 4 * max_frames:
                # bounded memory on long videos: halve the sampling rate as we go (what
                # is kept stays about evenly spaced; the final pick below evens it out)
                kept = kept[::2]
                if every is not None:
                    every *= 2
                else:
                    fps /= 2
                    next_t = (np.floor(t * fps + 1e-6) + 1) / fps
    if not kept:
        raise VideoError(f"no frames could be decoded from {path}")
    kept = _evenly(kept, max_frames)
    names, out = set(), []
    for t, img in kept:
        name = frame_name(path.stem, t)
        while name in names:  # two frames within a millisecond (variable frame rate)
            name += "_"
        names.add(name)
        out.append(VideoFrame(name=name, time=t, image=img.convert("RGB")))
    return out
