"""The holographic eye's gallery, after Novosad & Ziegler's figs. 3.1 and 3.2.

Run from the repository root: ``python reports/holographic/gallery.py [N] [ITERATIONS]``
(default 256 and 64). Writes ``gallery.png`` and ``gallery.md`` beside this file: the input
frame, then the eye with the base layer (pupil and lens), with lids and lashes, and with
lashes and a sinusoidal tear film (the paper's regular pattern), each averaged over the
iterations (top row) and as the speckle-free limit (bottom row), tone-mapped alike
(Reinhard's global operator with one key and white point for all panels).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import jax
import numpy as np

from invglare.aperture.eye import EyeAperture, Eyelashes, Eyelids, Pupil
from invglare.models.holographic import HolographicEye
from invglare.optics.holographic import TearFilm
from invglare.render.scenes import street_lights_at_night
from invglare.render.tonemap import reinhard_display

HERE = Path(__file__).resolve().parent
COLUMNS = {
    "base": ("pupil", "lens"),
    "+ lashes": ("lashes", "pupil", "lens"),
    "+ lashes + tear film": ("lashes", "tear_film", "pupil", "lens"),
}


def main(n: int = 256, iterations: int = 64) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    eye = EyeAperture(
        pupil=Pupil(3.0),
        lids=Eyelids(1.6, 1.8, 0.0, 0.0, 0.04),
        upper_lashes=Eyelashes(
            count=40.0, n_max=48, key=7, lid="upper", angular_spread_deg=12.0,
            thickness_mm=0.06, length_mm=2.5, curvature_per_mm=0.05, root_span_mm=8.0,
        ),
    )  # fmt: skip
    film = TearFilm(0.3, 1.0, pattern="sinusoid", angle_deg=20.0)
    frame, _ = street_lights_at_night(n, seed=0)
    frame = np.asarray(frame)
    white = float(frame.max()) * 0.02
    shown = {"input": frame}
    limits = {}
    timings = {}
    for name, layers in COLUMNS.items():
        model = HolographicEye.build(
            eye, npix=n, window_mm=8.0, focus_distance_mm=2000.0, depth_mm=2000.0,
            tear_film=film, layers=layers, iterations=iterations, psf_tiles=4,
        )  # fmt: skip
        t0 = time.perf_counter()
        shown[name] = np.asarray(model.render(frame, key=jax.random.key(0)))
        timings[name] = time.perf_counter() - t0
        limits[name] = np.asarray(model.speckle_free_image(frame))
    fig, axes = plt.subplots(2, 4, figsize=(16, 8.4))
    for ax in axes.ravel():
        ax.set_axis_off()
    for i, (name, img) in enumerate(shown.items()):
        axes[0, i].imshow(np.asarray(reinhard_display(img, 0.18, white)))
        title = name if name == "input" else f"{name} ({iterations} iterations)"
        axes[0, i].set_title(title)
    for i, (name, img) in enumerate(limits.items(), start=1):
        axes[1, i].imshow(np.asarray(reinhard_display(img, 0.18, white)))
        axes[1, i].set_title(f"{name} (speckle-free limit)")
    fig.suptitle(
        f"Holographic eye, {n} x {n}: 3 mm pupil, lashes 8 mm in front, focus 2 m; "
        f"{n * model.pixel_scale_deg:.2f} deg field"
    )
    fig.tight_layout()
    fig.savefig(HERE / "gallery.png", dpi=80)
    lines = [
        "# Holographic eye gallery",
        "",
        "After Novosad & Ziegler's figs. 3.1 / 3.2: input, base layer (pupil and lens), "
        "+ lids and lashes, + lashes and the paper's sinusoidal tear film (0.3 um, 1 mm, "
        "20 deg). Top: the average of the iterations; bottom: the speckle-free limit (4 x 4 "
        "PSF tiles). Made by `python reports/holographic/gallery.py "
        f"{n} {iterations}`.",
        "",
        "![gallery](gallery.png)",
        "",
        "| column | first render (s, with compilation) |",
        "|---|---:|",
        *[f"| {k} | {v:.1f} |" for k, v in timings.items()],
    ]
    (HERE / "gallery.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    args = [int(a) for a in sys.argv[1:]]
    main(*args)
