"""``invglare bench peers``: the same PSF in invglare and in dLux, hcipy and poppy, side by side.

Two PSFs, each at 550 nm on a 512 x 512 output with 128 samples across a 4 mm pupil and 4
pixels per lambda / D (the 128-sample pupil in a 512 FFT; the peers reach the same grid
with their matrix Fourier transforms):

- ``airy``: a clear disk, against `invglare.reference.closed_forms.airy_pixel_psf`;
- ``hexagon``: a regular hexagon of 4 mm corner-to-corner, a corner along +x, against
  `invglare.reference.closed_forms.polygon_far_field`.

Each code computes the PSF its own documented way (invglare: `AperturePSF` on the FFT path,
jitted; dLux: `AngularOpticalSystem` with a dynamic aperture, `equinox.filter_jit`, and,
as ``dlux_fft``, the same aperture on a bare `Wavefront` padded 4x and FFT'd; hcipy:
`FraunhoferPropagator` of a 4x supersampled aperture field, the field made once, only the
propagation timed; poppy: `OpticalSystem.calc_psf` with an MFT detector). Accuracy is
measured on each code's own output grid (hcipy and invglare put the axis on pixel 256,
dLux and poppy between the four central pixels) after scaling each PSF to the reference's
energy in the field (the codes normalise differently), as the largest and the rms pixel
difference over the reference's peak. The gradient, where the code has one (invglare and
dLux are JAX), is d(sum w * PSF)/d(pupil size) for fixed random weights w.

Every time is reported in milliseconds and as a ratio to the fastest bare 512 x 512
complex64 FFT (scipy, pyfftw, JAX) timed in the same run, with the load average and CPU
time over wall time of each measurement (the machine is shared). A peer that is not
installed is a row "not installed", not an error; install them with the ``bench`` extra.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import logging
import math
import os
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from invglare.bench.timing import load_1m

log = logging.getLogger("invglare")

#: Name of the case group (``invglare bench peers``).
PEER_CASES = ("peers",)
#: The codes compared, invglare first (the speed-ups are taken against it).
CODES = ("invglare", "dlux", "dlux_fft", "hcipy", "poppy")
SHAPES = ("airy", "hexagon")
NPIX = 512
PUPIL_SAMPLES = 128
PX_PER_LAMBDA_OVER_D = NPIX // PUPIL_SAMPLES  # 4
DIAMETER_MM = 4.0
WAVELENGTH_NM = 550.0
#: The same in metres, the unit of the peer codes.
_DIAMETER_M = DIAMETER_MM * 1e-3
_WAVELENGTH_M = WAVELENGTH_NM * 1e-9
#: The flags of /proc/cpuinfo that say which vector units XLA, numpy and FFTW can use.
VECTOR_FLAGS = (
    "sse4_2",
    "avx",
    "avx2",
    "fma",
    "avx512f",
    "avx512dq",
    "avx512bw",
    "avx512vl",
    "avx512_vnni",
    "avx512_bf16",
    "avx_vnni",
    "amx_tile",
    "neon",
    "asimd",
    "sve",
)


def cpu_info() -> dict[str, Any]:
    """The CPU's model name and vector extensions (Linux ``/proc/cpuinfo``; else the platform).

    **Returns:** ``{"model": str, "vector_extensions": [flag, ...], "logical_cpus": int}``;
    the extensions are those of `VECTOR_FLAGS` the first CPU lists.
    """
    import platform

    model, flags = None, set()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                key = key.strip().lower()
                if key in ("model name", "hardware", "cpu model") and model is None:
                    model = value.strip()
                elif key in ("flags", "features") and not flags:
                    flags = set(value.split())
    except OSError:
        pass
    model = model or platform.processor() or platform.machine()
    return {
        "model": model,
        "vector_extensions": [f for f in VECTOR_FLAGS if f in flags],
        "logical_cpus": os.cpu_count(),
    }


# ----------------------------------------------------------------------------- sampling


def pixel_scale_rad() -> float:
    """lambda / (4 D): 4 pixels per lambda / D."""
    return WAVELENGTH_NM * 1e-6 / (PX_PER_LAMBDA_OVER_D * DIAMETER_MM)


def output_coords_rad(centring: str) -> np.ndarray:
    """Pixel-centre angles of the 512 output pixels along one axis.

    ``"pixel"``: the axis on pixel ``NPIX // 2`` (invglare, hcipy); ``"corner"``: between
    pixels ``NPIX / 2 - 1`` and ``NPIX / 2`` (dLux's and poppy's MFT for an even size).
    """
    offset = 0.0 if centring == "pixel" else 0.5
    return (np.arange(NPIX) - NPIX // 2 + offset) * pixel_scale_rad()


def reference_psf(shape: str, centring: str) -> np.ndarray:
    """The closed form as energy per output pixel (sr^-1 at the centre times the solid angle)."""
    import jax

    from invglare.reference.closed_forms import (
        airy_psf,
        polygon_far_field,
        regular_polygon_vertices,
    )

    c = output_coords_rad(centring)
    with jax.enable_x64(True):
        if shape == "airy":
            theta = np.hypot(c[None, :], c[:, None])
            intensity = airy_psf(theta, DIAMETER_MM, WAVELENGTH_NM)
        else:
            vertices = regular_polygon_vertices(6, DIAMETER_MM)
            intensity = polygon_far_field(c[None, :], c[:, None], vertices, WAVELENGTH_NM)
        return np.asarray(intensity, np.float64) * pixel_scale_rad() ** 2


def psf_error(psf: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """Largest and rms pixel error over the reference's peak, `psf` scaled to its energy."""
    psf = np.asarray(psf, np.float64)
    scaled = psf * (reference.sum() / psf.sum())
    diff = scaled - reference
    peak = float(reference.max())
    return {
        "max_err": float(np.abs(diff).max() / peak),
        "rms_err": float(np.sqrt(np.mean(diff**2)) / peak),
        "energy_in_field": float(psf.sum()),
    }


# ----------------------------------------------------------------------------- the codes


@dataclasses.dataclass(frozen=True)
class PeerSetup:
    """One code's PSF: ``forward()`` → array, ``gradient()`` → its derivative (or None)."""

    forward: Callable[[], Any]
    gradient: Callable[[], Any] | None
    centring: str
    version: str
    how: str


def _weights():
    return np.random.default_rng(11).random((NPIX, NPIX)).astype(np.float32)


def _invglare(shape: str) -> PeerSetup:
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import invglare
    from invglare.aperture import Aperture, Disk, RegularPolygon
    from invglare.models.aperture_psf import AperturePSF

    shape_obj = Disk(DIAMETER_MM) if shape == "airy" else RegularPolygon(6, DIAMETER_MM)
    # The window is the pupil itself: 128 samples across D, padded to 512 by the FFT.
    model = AperturePSF.build(
        Aperture((shape_obj,)),
        focal_length_mm=17.0,
        wavelengths_nm=WAVELENGTH_NM,
        npix=NPIX,
        aperture_npix=PUPIL_SAMPLES,
        window_mm=DIAMETER_MM,
    )
    forward = jax.jit(lambda m: m())
    weights = jnp.asarray(_weights())

    def loss(diameter, m):
        m = eqx.tree_at(lambda m: m.aperture.shapes[0].diameter_mm, m, diameter)
        return jnp.sum(m() * weights)

    grad = jax.jit(jax.grad(loss))
    d0 = jnp.float32(DIAMETER_MM)
    version = getattr(invglare, "__version__", "")
    return PeerSetup(
        lambda: forward(model),
        lambda: grad(d0, model),
        "pixel",
        version,
        "AperturePSF (soft raster + real FFT), jax.jit; grad: d/d(diameter)",
    )


def _dlux(shape: str, method: str = "mft") -> PeerSetup | None:
    """dLux's PSF: ``"mft"`` its optical-system path (`AngularOpticalSystem`, the documented
    way to ask for an output grid), ``"fft"`` a bare `Wavefront` padded 4x and FFT'd (the
    same FFT sampling invglare uses)."""
    try:
        import dLux as dl
    except ImportError:
        return None
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    # dLux's polygon has a corner along +x, as the reference.
    aperture = (
        dl.CircularAperture(_DIAMETER_M / 2)
        if shape == "airy"
        else dl.RegPolyAperture(6, _DIAMETER_M / 2)
    )
    leaf = "radius" if shape == "airy" else "rmax"
    if method == "mft":
        system = dl.AngularOpticalSystem(
            wf_npixels=PUPIL_SAMPLES,
            diameter=_DIAMETER_M,
            layers=[("aperture", aperture)],
            psf_npixels=NPIX,
            psf_pixel_scale=math.degrees(pixel_scale_rad()) * 3600.0,
        )

        def psf(size):
            s = eqx.tree_at(lambda s: getattr(s.layers["aperture"], leaf), system, size)
            return s.propagate_mono(_WAVELENGTH_M)

        how, centring = "AngularOpticalSystem (MFT)", "corner"
    else:

        def psf(size):
            ap = eqx.tree_at(lambda a: getattr(a, leaf), aperture, size)
            wf = ap.apply(dl.Wavefront(_WAVELENGTH_M, PUPIL_SAMPLES, _DIAMETER_M))
            return wf.propagate_FFT(pad=PX_PER_LAMBDA_OVER_D).psf

        how, centring = "Wavefront + propagate_FFT(pad=4)", "pixel"
    forward = eqx.filter_jit(psf)
    weights = jnp.asarray(_weights())
    grad = eqx.filter_jit(jax.grad(lambda size: jnp.sum(psf(size) * weights)))
    r0 = jnp.float32(_DIAMETER_M / 2)
    return PeerSetup(
        lambda: forward(r0),
        lambda: grad(r0),
        centring,
        getattr(dl, "__version__", ""),
        f"{how}, equinox.filter_jit; grad: d/d({leaf})",
    )


def _hcipy(shape: str) -> PeerSetup | None:
    try:
        import hcipy as hc
    except ImportError:
        return None
    pupil = hc.make_pupil_grid(PUPIL_SAMPLES, _DIAMETER_M)
    # hcipy's hexagon has a corner along +y at angle 0; 30 deg puts one along +x.
    make = (
        hc.make_circular_aperture(_DIAMETER_M)
        if shape == "airy"
        else hc.make_hexagonal_aperture(_DIAMETER_M, angle=np.pi / 6)
    )
    field = hc.evaluate_supersampled(make, pupil, 4)
    focal = hc.make_focal_grid(
        q=PX_PER_LAMBDA_OVER_D, num_airy=NPIX // (2 * PX_PER_LAMBDA_OVER_D),
        spatial_resolution=_WAVELENGTH_M / _DIAMETER_M,
    )  # fmt: skip
    propagator = hc.FraunhoferPropagator(pupil, focal)

    def forward():
        return np.asarray(propagator(hc.Wavefront(field, _WAVELENGTH_M)).power.shaped)

    return PeerSetup(
        forward,
        None,
        "pixel",
        getattr(hc, "__version__", ""),
        "FraunhoferPropagator of a 4x supersampled aperture (made once); no gradient",
    )


def _poppy(shape: str) -> PeerSetup | None:
    try:
        import poppy
    except ImportError:
        return None
    system = poppy.OpticalSystem(oversample=1, npix=PUPIL_SAMPLES, pupil_diameter=_DIAMETER_M)
    # poppy's hexagon (side = corner radius) has a corner along +x.
    system.add_pupil(
        poppy.CircularAperture(radius=_DIAMETER_M / 2)
        if shape == "airy"
        else poppy.HexagonAperture(side=_DIAMETER_M / 2)
    )
    system.add_detector(
        pixelscale=math.degrees(pixel_scale_rad()) * 3600.0, fov_pixels=NPIX, oversample=1
    )

    def forward():
        return system.calc_psf(_WAVELENGTH_M)[0].data

    return PeerSetup(
        forward,
        None,
        "corner",
        getattr(poppy, "__version__", ""),
        "OpticalSystem.calc_psf (gray-pixel aperture, MFT detector); no gradient",
    )


SETUPS: dict[str, Callable[[str], PeerSetup | None]] = {
    "invglare": _invglare,
    "dlux": _dlux,
    "dlux_fft": lambda shape: _dlux(shape, "fft"),
    "hcipy": _hcipy,
    "poppy": _poppy,
}


# ----------------------------------------------------------------------------- the run


def _floor_functions() -> dict[str, Callable[[], Any]]:
    """The runner's bare 512 x 512 complex64 FFTs (scipy, pyfftw where installed, JAX)."""
    from invglare.bench.cases import CASES

    out = {}
    for case in CASES:
        if case.kind == "floor" or case.name == "fft_jax":
            fn = case.make(NPIX)
            if fn is not None:
                out[case.name] = fn
    return out


def measure_side_by_side(
    fns: dict[str, Callable[[], Any]], rounds: int, budget_s: float | None = None
) -> dict[str, dict[str, Any]]:
    """Time several callables in interleaved rounds (A B C, A B C, ...), after compiling each.

    On a shared machine the load changes from second to second; calling every function once
    per round spreads those changes evenly over all of them, which timing each in its own
    block (as `invglare.bench.timing.measure` does) cannot. Stops after `rounds`, or
    once `budget_s` seconds of rounds are spent (at least 3 rounds).

    **Returns:** per name ``median_ms``, ``min_ms``, ``repeats``, ``first_call_s``,
    ``cpu_per_wall`` (its own calls' process CPU time over their wall time) and ``load_1m``.
    """
    from invglare.bench.timing import _block

    first: dict[str, float] = {}
    for name, fn in fns.items():
        t0 = time.perf_counter()
        _block(fn())
        first[name] = time.perf_counter() - t0
        _block(fn())  # a warm-up call: FFT plans, allocator
    times: dict[str, list[float]] = {name: [] for name in fns}
    cpu = dict.fromkeys(fns, 0.0)
    started = time.perf_counter()
    for i in range(max(rounds, 3)):
        if budget_s is not None and i >= 3 and time.perf_counter() - started > budget_s:
            break
        for name, fn in fns.items():
            c0, t0 = time.process_time(), time.perf_counter()
            _block(fn())
            times[name].append((time.perf_counter() - t0) * 1e3)
            cpu[name] += time.process_time() - c0
    load = load_1m()
    return {
        name: {
            "median_ms": round(statistics.median(t), 4),
            "min_ms": round(min(t), 4),
            "repeats": len(t),
            "first_call_s": round(first[name], 3),
            "cpu_per_wall": round(cpu[name] / (sum(t) / 1e3), 2),
            "load_1m": load,
        }
        for name, t in times.items()
    }


def run_peer_benchmark(repeats: int = 20, budget_s: float = 30.0) -> dict[str, Any]:
    """Check and time every code on every shape; one record for bench.json's ``"fit"`` list.

    Per shape, the FFT floors and every installed code's forward and gradient calls are
    timed side by side (`measure_side_by_side`, `repeats` rounds, at most `budget_s`
    seconds of them).

    **Returns:** ``{"case": "peers", "kind": "peers", "date", "cpu", "jax", "setup",
    "load_1m_start", "load_1m_end", "rows": [...]}``; each row has the code, shape,
    version, how it was run, ``forward`` and ``gradient`` timings (``gradient`` None when
    the code has none), each with its ``ratio`` to the fastest floor of the same rounds
    and (peers) the ``speedup`` of invglare over it, the accuracy (`psf_error`), or
    ``status: "not installed"`` / ``"failed: ..."``. The floors' timings are in
    ``floors[shape]``.
    """
    import jax

    record: dict[str, Any] = {
        "case": "peers",
        "kind": "peers",
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu": cpu_info(),
        "jax": jax.__version__,
        "load_1m_start": load_1m(),
        "setup": {
            "npix": NPIX,
            "pupil_samples": PUPIL_SAMPLES,
            "px_per_lambda_over_d": PX_PER_LAMBDA_OVER_D,
            "diameter_mm": DIAMETER_MM,
            "wavelength_nm": WAVELENGTH_NM,
        },
        "floors": {},
    }
    rows = []
    for shape in SHAPES:
        references = {c: reference_psf(shape, c) for c in ("pixel", "corner")}
        floors = _floor_functions()
        fns: dict[str, Callable[[], Any]] = {f"floor:{k}": v for k, v in floors.items()}
        shape_rows = []
        for code in CODES:
            row: dict[str, Any] = {"code": code, "shape": shape}
            shape_rows.append(row)
            try:
                setup = SETUPS[code](shape)
                if setup is None:
                    row["status"] = "not installed"
                    continue
                row.update(version=setup.version, how=setup.how)
                log.info("peers: checking %s on the %s PSF", code, shape)
                row.update(psf_error(np.asarray(setup.forward()), references[setup.centring]))
                row["status"] = "ok"
                fns[f"{code}:forward"] = setup.forward
                if setup.gradient is not None:
                    fns[f"{code}:gradient"] = setup.gradient
            except Exception as err:  # one broken peer must not lose the others' rows
                log.error("peer %s (%s) failed: %s", code, shape, err)
                row["status"] = f"failed: {type(err).__name__}: {err}"
        log.info("peers: timing %d calls side by side on the %s PSF", len(fns), shape)
        timings = measure_side_by_side(fns, repeats, budget_s)
        floor_ms = min(timings[f"floor:{k}"]["median_ms"] for k in floors)
        record["floors"][shape] = {k: timings[f"floor:{k}"] for k in floors}
        for row in shape_rows:
            if row.get("status") != "ok":
                continue
            for part in ("forward", "gradient"):
                timing = timings.get(f"{row['code']}:{part}")
                if timing is not None:
                    timing["ratio"] = round(timing["median_ms"] / floor_ms, 2)
                    timing["floor_ms"] = floor_ms
                row[part] = timing
        rows += shape_rows
        fns = floors = None
        jax.clear_caches()
    _add_speedups(rows)
    record["rows"] = rows
    record["load_1m_end"] = load_1m()
    return record


def _add_speedups(rows: list[dict]) -> None:
    """``speedup`` (``speedup_min``): the peer's median (minimum) over invglare's, per shape
    and part (in place)."""
    ours = {(r["shape"]): r for r in rows if r["code"] == "invglare" and r.get("status") == "ok"}
    for r in rows:
        base = ours.get(r["shape"])
        if base is None or r.get("status") != "ok" or r["code"] == "invglare":
            continue
        for part in ("forward", "gradient"):
            if r.get(part) and base.get(part):
                r[part]["speedup"] = round(r[part]["median_ms"] / base[part]["median_ms"], 2)
                # Minima suffer least from the other processes: the floor of each code's time.
                r[part]["speedup_min"] = round(r[part]["min_ms"] / base[part]["min_ms"], 2)


def _cell(timing: dict | None) -> str:
    if not timing:
        return "n/a"
    text = f"{timing['median_ms']:.2f} ms, min {timing['min_ms']:.2f} ({timing['ratio']:.1f}x)"
    if "speedup" in timing:
        text += (
            f", invglare {timing['speedup']:.1f}x faster (by minima {timing['speedup_min']:.1f}x)"
        )
    return text


def peers_markdown(record: dict) -> list[str]:
    """bench.md's peers section: the setup, the machine and one row per code and shape."""
    cpu = record.get("cpu", {})
    floor_text = "; ".join(
        f"{shape}: "
        + ", ".join(
            f"{k} {v['median_ms']:.3f} ms, min {v['min_ms']:.3f}" for k, v in floors.items()
        )
        for shape, floors in record.get("floors", {}).items()
    )
    lines = [
        "## Peers: the same PSF in dLux, hcipy and poppy",
        "",
        f"Measured {record.get('date')} on {cpu.get('model', '?')} "
        f"({', '.join(cpu.get('vector_extensions', [])) or 'no vector flags read'}; "
        f"{cpu.get('logical_cpus')} logical CPUs), JAX {record.get('jax')}; load average "
        f"(1 min) {record.get('load_1m_start')} at the start, {record.get('load_1m_end')} at "
        f"the end (above {cpu.get('logical_cpus')}, other processes competed for the cores).",
        "",
        f"{NPIX} x {NPIX} PSF at {WAVELENGTH_NM:g} nm, {PUPIL_SAMPLES} samples across a "
        f"{DIAMETER_MM:g} mm pupil, {PX_PER_LAMBDA_OVER_D} px per lambda / D. Times are medians "
        "(and minima) after compilation, all calls of a shape timed in interleaved rounds, "
        "with their ratio to the fastest bare 512 x 512 complex64 FFT of the same rounds "
        f"in brackets ({floor_text}). Errors: "
        "largest and rms pixel difference from the closed form (Airy; polygon far field) over "
        "its peak, on each code's own grid, each PSF scaled to the closed form's energy in the "
        "field. Gradient: d(sum w * PSF)/d(pupil size). 'invglare Nx faster': the peer's median "
        "over invglare's, same shape and part (and the same for the minima).",
        "",
        "| shape | code | forward | gradient | max err | rms err | cpu/wall | load | how |",
        "|---|---|---|---|---:|---:|---:|---:|---|",
    ]
    for r in record.get("rows", []):
        if r.get("status") != "ok":
            lines.append(f"| {r['shape']} | {r['code']} | {r.get('status')} | | | | | | |")
            continue
        fwd = r["forward"]
        lines.append(
            f"| {r['shape']} | {r['code']} {r.get('version', '')} | {_cell(fwd)} "
            f"| {_cell(r.get('gradient'))} | {r['max_err']:.2e} | {r['rms_err']:.2e} "
            f"| {fwd['cpu_per_wall']:.2f} | {fwd['load_1m']} | {r.get('how', '')} |"
        )
    return lines
