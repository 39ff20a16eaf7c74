"""A frame and its depth buffer from EXR files, for the holographic eye.

The depth comes from a ``Z`` channel of the frame's own EXR (the OpenEXR convention for
depth), from a separate EXR (its ``Z``, ``Y`` or single channel), or not at all (the model
then uses one constant depth). Values are read as stored; the model's
:class:`~invglare.optics.holographic.Frustum` says how to decode them (planar depth in
metres by default, or a normalised z-buffer with near and far planes).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from invglare.errors import InputDataError
from invglare.files.exr import read_exr

__all__ = ["FrameWithDepth", "read_frame_and_depth"]

#: Channel names read as depth, in order of preference.
DEPTH_CHANNELS = ("Z", "depth", "Y")


@dataclass(frozen=True)
class FrameWithDepth:
    """What :func:`read_frame_and_depth` returns.

    - `frame`: ``(H, W, 3)`` linear RGB (float32), or ``(H, W)`` for a mono frame.
    - `depth`: ``(H, W)`` depth-buffer values, or None when there is no depth.
    - `pixel_scale_deg`: the frame's ``pixelScaleDeg`` header, if any.
    - `depth_source`: where the depth came from (for messages and reports).
    """

    frame: np.ndarray
    depth: np.ndarray | None
    pixel_scale_deg: float | None
    depth_source: str


def _depth_plane(data: np.ndarray, channels: tuple[str, ...], path: Path) -> np.ndarray:
    if data.ndim == 2:
        return data
    for name in DEPTH_CHANNELS:
        if name in channels:
            return data[..., channels.index(name)]
    if data.shape[-1] == 1:
        return data[..., 0]
    raise InputDataError(
        f"{path}: no depth channel; expected one of {', '.join(DEPTH_CHANNELS)} or a single "
        f"channel, the file has {list(channels)}"
    )


def read_frame_and_depth(
    path: str | os.PathLike[str], depth_path: str | os.PathLike[str] | None = None
) -> FrameWithDepth:
    """Read an HDR frame and its depth buffer (a ``Z`` channel or a separate EXR).

    **Arguments:**

    - `path`: the frame's EXR; ``R, G, B`` (and optionally ``Z``), or a lone ``Y``.
    - `depth_path`: a separate EXR holding the depth (``Z``, ``depth``, ``Y`` or one
      channel); it wins over a ``Z`` channel of the frame.

    **Returns:** a :class:`FrameWithDepth`.

    **Raises:** `InputDataError` naming the file for a missing or unreadable file, bad
    pixels (:func:`invglare.files.exr.read_exr`), a depth file without a depth channel, or a
    depth buffer of another size than the frame (both sizes named).

    **Example:**

    ```python
    got = read_frame_and_depth("scene.exr", "depth.exr")
    img = model.render(got.frame, got.depth, key=0)
    ```
    """
    src = Path(path)
    exr = read_exr(src)
    channels = exr.channels
    data = exr.data
    depth = None
    source = "none (constant depth)"
    if data.ndim == 3 and {"R", "G", "B"} <= set(channels):
        frame = data[..., [channels.index(c) for c in ("R", "G", "B")]]
        if "Z" in channels:
            depth, source = data[..., channels.index("Z")], f"{src} (Z channel)"
    elif data.ndim == 2:
        frame = data
    else:
        raise InputDataError(
            f"{src}: a frame needs R, G, B (or a lone Y) channels, the file has {list(channels)}"
        )
    if depth_path is not None:
        dsrc = Path(depth_path)
        dexr = read_exr(dsrc)
        depth, source = _depth_plane(dexr.data, dexr.channels, dsrc), str(dsrc)
    if depth is not None and depth.shape != frame.shape[:2]:
        raise InputDataError(
            f"depth from {source} is {depth.shape[1]} x {depth.shape[0]} px but the frame "
            f"{src} is {frame.shape[1]} x {frame.shape[0]} px; they must be the same size"
        )
    return FrameWithDepth(
        frame=np.ascontiguousarray(frame, dtype=np.float32),
        depth=None if depth is None else np.ascontiguousarray(depth, dtype=np.float32),
        pixel_scale_deg=exr.pixel_scale_deg,
        depth_source=source,
    )
