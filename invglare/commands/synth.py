"""``invglare synth``: synthetic target photos with their ground truth.

For each spec (:mod:`invglare.config.synth`) the model's PSF is computed in
float64, turned into mean counts by the observation (flux, background, offset,
rotation, response), and a noisy photo is drawn from it (Poisson electrons,
Gaussian read noise, hard clip at the saturation level) with the spec's seed.
Two files are written atomically next to the spec:

- ``NAME.exr``: channel ``Y`` in counts, ``pixelScaleDeg`` (the photo's),
  ``wavelengthsNm``, the full model config (``invglareConfig``) and the
  observation and noise seed (``invglareObservation``, ``invglareNoiseSeed``);
- ``NAME.truth.json``: the same model config, observation and seed, plus a few
  statistics of the photo. :func:`invglare.config.fit.load_fit` reads it to
  report the error of each fitted parameter.

The same spec and seed give byte-identical files.

**Example:**

```bash
invglare synth data_synthetic/eye_daylight.toml
```
"""

from __future__ import annotations

import logging
from pathlib import Path

from invglare.config.synth import SynthSpec, load_synth_specs
from invglare.config.synth_photo import (
    HALF_MAX_ERROR_SIGMA,
    TRUTH_FORMAT,
    TRUTH_VERSION,
    build_truth_forward,
    observation_table,
    synthesize,
    write_synth,
)

log = logging.getLogger("invglare")

__all__ = [
    "HALF_MAX_ERROR_SIGMA",
    "TRUTH_FORMAT",
    "TRUTH_VERSION",
    "build_truth_forward",
    "observation_table",
    "run_synth",
    "synthesize",
    "write_population_tables",
    "write_synth",
]


def run_synth(specs: list[Path], out_dir: Path | None = None) -> list[Path]:
    """Synthesise every spec in turn. **Returns:** the photos written."""
    from tqdm import tqdm

    from invglare.files.outputs import output_file, output_folder

    if out_dir is not None:
        output_folder(out_dir, "--out-dir")
    # Every spec is checked before any work; a population spec gives one per member.
    parsed = [member for p in specs for member in load_synth_specs(p, out_dir)]
    for spec in parsed:
        where = "--out-dir" if out_dir is not None else f"the folder of {spec.path}"
        output_file(spec.out_exr, where, (".exr",))
        output_file(spec.out_truth, where, (".json",))
    written = []
    for spec in tqdm(parsed, desc="synth", unit="photo", disable=len(parsed) < 2):
        photo, truth = synthesize(spec)
        exr, truth_file = write_synth(spec, photo, truth)
        stats = truth["stats"]
        log.info(
            "wrote %s (%dx%d, %.5g deg/px, max %.6g counts, %d clipped pixels) and %s",
            exr,
            photo.shape[0],
            photo.shape[1],
            truth["pixel_scale_deg"],
            stats["max_counts"],
            stats["saturated_pixels"],
            truth_file.name,
        )
        written.append(exr)
    write_population_tables([spec for spec in parsed if spec.drawn])
    return written


def write_population_tables(members: list[SynthSpec]) -> list[Path]:
    """``population.csv`` in each population's folder: per member its photo, noise seed
    and drawn values (the truth of each is in its ``NAME.truth.json``). **Returns:** paths."""
    import csv
    import io

    from invglare.files.atomic import write_text_atomic

    folders: dict[Path, list[SynthSpec]] = {}
    for spec in members:
        folders.setdefault(spec.out_dir, []).append(spec)
    written = []
    for folder, group in folders.items():
        keys = list(dict.fromkeys(k for spec in group for k in spec.drawn))
        buffer = io.StringIO()
        out = csv.writer(buffer, lineterminator="\n")
        out.writerow(["photo", "noise_seed", *keys])
        for spec in group:
            out.writerow([spec.out_exr.name, spec.seed, *(spec.drawn.get(k, "") for k in keys)])
        written.append(write_text_atomic(folder / "population.csv", buffer.getvalue()))
        log.info("wrote %s (%d members)", folder / "population.csv", len(group))
    return written
