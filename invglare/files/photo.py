"""Reading a photo to fit: one monochrome plane of linear counts, as float64.

:func:`read_photo` reads any format :func:`~invglare.files.images.read_image` reads and
refuses, with the reason, what cannot be linear counts of one channel: a missing file,
a display-encoded integer image (8-bit PNG/JPEG, integer TIFF: tone-mapped) unless the
caller knows it to be linear, a multi-channel image without a channel named, a channel
it does not have, and (for a square model grid) a non-square image. What the counts
themselves must satisfy (finite, not constant, not all clipped) is checked by the fit
(:func:`invglare.fit.check_target`).

**Example:**

```python
data, pixel_scale_deg = read_photo(Path("data_synthetic/eye_daylight.exr"))
data.shape, pixel_scale_deg        # (256, 256), 0.003
```
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from jaxtyping import Float

from invglare.errors import InputDataError
from invglare.files.images import read_image


def read_photo(
    path: Path,
    *,
    channel: str | None = None,
    linear: bool = False,
    square: bool = True,
) -> tuple[Float[np.ndarray, "h w"], float | None]:
    """Read one plane of a photo as float64 counts; **returns** ``(image, pixelScaleDeg or None)``.

    **Arguments:**

    - `path`: the photo (EXR, float TIFF; or an integer file known to be linear).
    - `channel`: which channel of a multi-channel file (``"Y"``, ``"R"``, ...).
    - `linear`: accept a display-encoded (integer) file as linear counts: its integer
      codes are the counts.
    - `square`: refuse a non-square image (the PSF models' output grids are square).

    **Raises:** :class:`~invglare.errors.InputDataError` naming the file and the reason
    (see the module docstring).
    """
    if not path.exists():
        raise InputDataError(f"target photo {path} does not exist")
    image = read_image(path, allow_negative=True)
    data = np.asarray(image.data, dtype=np.float64)
    if image.display_encoded:
        if not linear:
            depth = f"{image.bit_depth}-bit " if image.bit_depth else ""
            raise InputDataError(
                f"target photo {path} is a {depth}{path.suffix.lstrip('.').upper()} image, "
                "display-encoded (gamma / tone-mapped), not linear counts; fit a linear photo "
                "(raw converted to OpenEXR or float TIFF), or set target.linear = true if this "
                "file is known to hold linear values"
            )
        # Integer codes were scaled to [0, 1] on reading; a linear file's counts are the codes.
        data = data * float(2 ** (image.bit_depth or 8) - 1)
    if data.ndim == 3:
        names = list(image.channels)
        if channel is None:
            raise InputDataError(
                f"target photo {path} has channels {', '.join(names)}; choose one with "
                "target.channel (fits use one monochrome channel)"
            )
        if channel not in names:
            raise InputDataError(
                f"target photo {path} has no channel {channel!r}; it has {', '.join(names)}"
            )
        data = data[..., names.index(channel)]
    elif channel is not None and channel not in image.channels:
        raise InputDataError(
            f"target photo {path} has no channel {channel!r}; it has {', '.join(image.channels)}"
        )
    if data.ndim != 2 or (square and data.shape[0] != data.shape[1]):
        raise InputDataError(
            f"target photo {path} is {data.shape[1]}x{data.shape[0]} pixels; crop it to a "
            "square centred on the light source (the model's output grid is square)"
        )
    return data, image.pixel_scale_deg
