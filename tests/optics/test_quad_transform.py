"""The quad transforms against closed forms and against the discrete transforms.

Closed forms (float64): a box's far field is sinc², a square's near field is the Fresnel
integrals' product, a disk's far field is the Airy pattern; identities: the quad far field
of a raster is its MFT times the pixel's own transfer function, at any sampling.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import x64

from invglare._core.grids import AngularGrid, ApertureGrid
from invglare.aperture import Aperture, Disk
from invglare.optics.fraunhofer import fraunhofer_mft, transmitted_power
from invglare.optics.quad import (
    build_quadtree,
    detect_mirrors,
    make_plan,
    quad_far_field,
    quad_near_field,
    sinc,
)
from invglare.optics.quad.apertures import PAPER_APERTURES, paper_grid, paper_raster
from invglare.optics.quad.cull import (
    MAX_EVALUATED,
    cull_tiles,
    culling_error,
    evaluated_fraction,
    kept_fraction,
)
from invglare.optics.quad.farfield import plan_amplitudes
from invglare.optics.quad.outline import Piece
from invglare.optics.quad.polygon import polygon_transform, series_points
from invglare.optics.quad.prepare import half_plane_freqs, pieces_transform
from invglare.optics.quad.transform import box_kernel
from invglare.reference.closed_forms import (
    airy_pixel_psf,
    fresnel_square_intensity,
    polygon_fourier_transform,
    rect_psf,
    regular_polygon_vertices,
)

LAM = 550.0


def _plan(raster, symmetric=True):
    layout = build_quadtree(np.asarray(raster))
    mirrors = detect_mirrors(np.asarray(raster)) if symmetric else (False, False)
    return make_plan(layout, *mirrors)


def _step(grid: ApertureGrid, out: AngularGrid, lam=LAM) -> float:
    return float(out.pixel_scale_rad * grid.pitch_mm / (lam * 1e-6))


# ---------------------------------------------------------------------------------- sinc


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_sinc_value_and_derivative_are_exact_near_zero(dtype):
    """Series branch below |pi x| = 1: value and derivative against the closed forms
    (evaluated in float64 from the Taylor series near 0, directly elsewhere)."""
    with x64():
        x = np.array([0.0, 1e-8, 1e-5, 1e-3, 0.05, 0.3, 0.31831, 0.32, 0.9, 2.5], dtype)
        value = np.asarray(sinc(jnp.asarray(x)))
        grad = np.asarray(jax.vmap(jax.grad(sinc))(jnp.asarray(x)))
        y = np.pi * x.astype(np.float64)
        safe = np.where(y == 0, 1.0, y)
        exact = np.where(y == 0, 1.0, np.sin(safe) / safe)
        # d/dx sin(pi x)/(pi x) = pi (y cos y - sin y) / y^2, whose small-y series is -pi y / 3.
        direct = np.pi * (y * np.cos(y) - np.sin(y)) / safe**2
        series = -np.pi * (y / 3 - y**3 / 30 + y**5 / 840)
        exact_grad = np.where(np.abs(y) < 0.05, series, direct)
    tol = 3e-7 if dtype == np.float32 else 1e-14
    np.testing.assert_allclose(value, exact, rtol=tol, atol=tol)
    np.testing.assert_allclose(grad, exact_grad, rtol=tol, atol=tol)


# --------------------------------------------------------------------------- far field


def test_box_far_field_is_sinc_squared_to_1e6_of_peak():
    """A 33 x 21 px box aligned with the pixels, centred on the grid origin: its quads are
    the box exactly, so the far field is sinc² (closed_forms.rect_psf) at any sampling,
    here 3x finer than the FFT's and out to 1.5x the raster's Nyquist angle."""
    with x64():
        n, pitch = 64, 0.05
        raster = np.zeros((n, n))
        raster[n // 2 - 10 : n // 2 + 11, n // 2 - 16 : n // 2 + 17] = 1.0
        grid = ApertureGrid(n, pitch)
        nyquist = LAM * 1e-6 / (2 * pitch)
        out = AngularGrid(193, math.degrees(1.5 * nyquist / 96))
        psf = np.asarray(quad_far_field(_plan(raster), jnp.asarray(raster), _step(grid, out), 193))
        theta = np.asarray(out.coords_rad())
        ref = np.asarray(
            rect_psf(theta[None, :], theta[:, None], 33 * pitch, 21 * pitch, LAM)
        ) * float(out.solid_angle_sr())
    assert np.max(np.abs(psf - ref)) < 1e-6 * ref.max()


@pytest.mark.parametrize("name", PAPER_APERTURES)
@pytest.mark.parametrize("npix", [63, 96])
def test_quad_far_field_is_mft_times_pixel_transfer_to_1e5_of_peak(name, npix):
    """float32, the four paper apertures (64 px), symmetric fast path and plain, odd and
    even outputs, the field reaching twice the raster's Nyquist angle."""
    n = 64
    raster = paper_raster(name, n).astype(np.float32)
    grid = paper_grid(n)
    nyquist = LAM * 1e-6 / (2 * float(grid.pitch_mm))
    out = AngularGrid(npix, math.degrees(2.0 * nyquist / (npix // 2)))
    step = _step(grid, out)
    mft = np.asarray(fraunhofer_mft(jnp.asarray(raster), grid, LAM, out))
    f = (np.arange(npix) - npix // 2) * step
    transfer = (np.sinc(f)[:, None] * np.sinc(f)[None, :]) ** 2
    ref = mft * transfer
    for symmetric in (True, False):
        psf = np.asarray(quad_far_field(_plan(raster, symmetric), jnp.asarray(raster), step, npix))
        assert np.max(np.abs(psf - ref)) < 1e-5 * ref.max(), (name, symmetric)


@pytest.mark.parametrize(
    ("name", "npix", "mirrors"),
    [("box", 1024, (True, True)), ("circle", 2048, (True, True)),
     ("heptagon", 1024, (False, True)), ("heptagon", 2048, (False, True)),
     ("whirl", 256, (False, False))],
)  # fmt: skip
def test_float32_soft_rasters_keep_their_mirrors(name, npix, mirrors):
    """Rounding in a float32 coverage raster (up to 2.3e-4 per edge pixel at 2048 px, more
    than the old per-pixel tolerance of 1e-4) is not an asymmetry."""
    raster = paper_raster(name, npix).astype(np.float32)
    assert detect_mirrors(raster) == mirrors


@pytest.mark.parametrize("factor", [0.9, 1.1])
def test_mirror_tolerance_bounds_the_far_field_error(factor):
    """An odd part of `factor` times the tolerance (in sum over the raster's sum): below it
    the mirror is used, and the PSF then differs from the full evaluation's by less than
    twice the tolerance of its peak (and visibly: the odd part is really skipped)."""
    tolerance = 1e-3
    n = 64
    raster = paper_raster("heptagon", n)  # even in y
    bump = np.zeros_like(raster)
    bump[20, 26] = 1.0  # one pixel with no mirror partner above
    # Its odd part is +-1/2 at it and at its (empty) mirror image: 1 in sum.
    raster = raster + bump * factor * tolerance * raster.sum()
    mirrors = detect_mirrors(raster, tolerance)
    assert mirrors == (False, factor < 1.0)
    if factor > 1.0:
        return
    layout = build_quadtree(raster)
    grid = paper_grid(n)
    out = AngularGrid(96, math.degrees(LAM * 1e-6 / (96 * float(grid.pitch_mm))))
    step = _step(grid, out)
    with x64():
        field = jnp.asarray(raster)
        fast = np.asarray(quad_far_field(make_plan(layout, *mirrors), field, step, 96))
        full = np.asarray(quad_far_field(make_plan(layout), field, step, 96))
    error = np.max(np.abs(fast - full)) / full.max()
    assert 1e-2 * tolerance < error < 2.0 * tolerance


def test_disk_matches_airy_as_well_as_the_mft_does():
    """A 4 mm disk on 128 px (soft raster): the MFT, the raster's quads, the exact ellipse
    piece and a 512-gon against the Airy pattern per pixel (float64; the rasters' power
    matched to the disk's area, see tests/reference: a grey edge transmits c but c²).

    Measured (of the peak): MFT 2.9e-5, 512-gon 1.6e-5, ellipse 1e-16; the raster's quads
    5.7e-5. A coverage raster is the disk averaged over pixels (the MFT carries that
    pixel's transfer function S once); read as boxes it carries S twice, which at the
    first ring (f = 0.013 cycles/px) is 1e-3 of the ring's 0.0175: 2e-5 of the peak, the
    difference. So the polygon path beats the MFT and the raster's quads are within a
    factor 2 of it."""
    with x64():
        d, n = 4.0, 136
        grid = ApertureGrid(n, d / 128)
        raster = Aperture((Disk(d),)).transmission(grid)
        out = AngularGrid(96, math.degrees(LAM * 1e-6 / (4 * d)))
        ref = np.asarray(airy_pixel_psf(out, d, LAM))
        match = float(transmitted_power(raster, grid.pitch_mm)) / (math.pi * d * d / 4)
        mft = np.asarray(fraunhofer_mft(raster, grid, LAM, out)) * match
        quad = np.asarray(quad_far_field(_plan(raster), raster, _step(grid, out), 96)) * match
        fy, fx = half_plane_freqs(out, LAM)
        h = 48
        scale = (float(out.pixel_scale_rad) / (LAM * 1e-6)) ** 2
        errors = {}
        for name, piece in (
            ("ellipse", Piece("ellipse", 1.0, None, jnp.zeros(2), jnp.full(2, d / 2), 0.0)),
            ("512-gon", Piece("polygon", 1.0, regular_polygon_vertices(512, d))),
        ):
            at = series_points(np.asarray(fy), np.asarray(fx), d / 4)
            f = np.asarray(pieces_transform([piece], fy, fx, at))
            area = float(np.real(f[0, h]))
            block = np.abs(f) ** 2 * scale / area
            psf = np.concatenate([block[h:0:-1, ::-1][:, :96], block[:h, :96]], axis=0)
            errors[name] = np.max(np.abs(psf - ref)) / ref.max()
    peak = ref.max()
    err_mft = np.max(np.abs(mft - ref)) / peak
    err_quad = np.max(np.abs(quad - ref)) / peak
    assert err_quad <= 2.1 * err_mft < 1e-4
    assert errors["ellipse"] < 1e-12
    assert errors["512-gon"] <= err_mft


def test_polygon_transform_matches_the_independent_reference():
    """Optics' polygon transform (stable sinc, centroid fan series) against
    reference.closed_forms (origin fan, jnp.sinc), including frequencies near 0 and
    exactly along the edge normals, in float64."""
    with x64():
        v = regular_polygon_vertices(7, 4.0, 10.0) + jnp.asarray([0.3, -0.2])
        for f in (jnp.linspace(-20, 20, 81), jnp.linspace(-0.05, 0.05, 21)):
            ours = polygon_transform(v, f, f)
            ref = polygon_fourier_transform(f[None, :], f[:, None], v)
            assert float(jnp.max(jnp.abs(ours - ref))) < 1e-12


# --------------------------------------------------------------------------- near field


def _square_near_setup(fresnel_number, ratio, npix=101):
    """The 41 px square of the test above at a Fresnel number, observed with an output pixel
    of `ratio` raster pixels at the distance: (plan, field, step, alpha, reference PSF)."""
    n, side_px, pitch = 64, 41, 0.025
    s = side_px * pitch
    raster = np.zeros((n, n))
    lo = n // 2 - side_px // 2
    raster[lo : lo + side_px, lo : lo + side_px] = 1.0
    d = s * s / (LAM * 1e-6 * fresnel_number)
    dtheta = ratio * pitch / d
    step = dtheta * pitch / (LAM * 1e-6)
    alpha = pitch * pitch / (LAM * 1e-6 * d)
    xs = (np.arange(npix) - npix // 2) * dtheta * d
    ref = fresnel_square_intensity(xs[None, :], xs[:, None], s, LAM, d) * (d * dtheta) ** 2
    return _plan(raster), raster, step, alpha, ref / (s * s)


@pytest.mark.parametrize("fresnel_number", [1, 5, 20])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_square_near_field_matches_fresnel_integrals_to_1e4_of_peak(fresnel_number, dtype):
    """A 41 px square (binary, centred) at Fresnel numbers s²/(lambda z) of 1, 5, 20,
    observed over 1.5 times its width. The quads are the square exactly, so the only
    error is round-off (measured 3e-15 in float64, 2e-6 in float32); the chirp-sampled
    MFT of the same raster errs 3e-4, 5e-3 and 5e-2 of the peak (FresnelMFT)."""
    with x64():
        # Output pixel 0.75 s / 50 at the distance: 0.615 raster pixels.
        plan, raster, step, alpha, ref = _square_near_setup(fresnel_number, 0.615)
        field = jnp.asarray(raster, dtype)
        psf = quad_near_field(plan, field, dtype(step), dtype(alpha), 101)
    assert np.max(np.abs(np.asarray(psf, np.float64) - ref)) < 1e-4 * ref.max()


@pytest.mark.parametrize("ratio", [1.0, 2.0, 0.5])
@pytest.mark.parametrize("fresnel_number", [1, 5, 20])
def test_square_near_field_by_the_lattice_table_matches_fresnel_integrals(fresnel_number, ratio):
    """The lattice table (the Fresnel integrals once per distinct argument, for an output
    pixel of `ratio` raster pixels at the distance; 1: the raster's own grid) gives the
    closed form to 1e-10 of the peak in float64, and the whole table's field to 1e-12."""
    from invglare.optics.quad.nearfield import lattice_ratio

    with x64():
        plan, raster, step, alpha, ref = _square_near_setup(fresnel_number, ratio)
        assert lattice_ratio(step / alpha) == ratio
        field = jnp.asarray(raster)
        psf = np.asarray(quad_near_field(plan, field, step, alpha, 101, ratio=ratio))
        whole = np.asarray(quad_near_field(plan, field, step, alpha, 101))
    assert np.max(np.abs(psf - ref)) < 1e-10 * ref.max()
    assert np.max(np.abs(psf - whole)) < 1e-12 * ref.max()


@pytest.mark.parametrize(
    ("name", "symmetric"), [("whirl", False), ("heptagon", True), ("circle", True)]
)
@pytest.mark.parametrize("ratio", [None, 1.0])
def test_near_field_by_corners_equals_the_sum_over_quad_intervals(name, symmetric, ratio):
    """float64, the paper's anti-aliased apertures at 64 px: the near field's parity terms
    summed over the quads' corners (edge kernel, dense corner matrix: what
    ``quad_near_field`` evaluates) equal the sum over the quads' intervals (interval kernel,
    per-quad gathers) to 1e-12 of the largest term, with the mirrors (skipped terms) and
    without, by the whole table and by the lattice table (ratio 1: the raster's own grid)."""
    from invglare.optics.quad.nearfield import corner_plan, fresnel_kernel, near_field_terms
    from invglare.optics.quad.transform import quadrant_terms

    with x64():
        raster = np.asarray(paper_raster(name, 64), np.float64)
        plan = _plan(raster, symmetric=symmetric)
        assert (plan.mirror_x or plan.mirror_y) == symmetric
        corners, source, factor = corner_plan(plan)
        assert corners.dense_inner and corners.n_rows <= 33 and corners.n_cols <= 33
        assert source.size == 4 * plan.quad_row.size and set(np.abs(factor)) == {1.0}
        amps, _ = plan_amplitudes(plan, jnp.asarray(raster))
        alpha = 4.0 * 10.0 / 60.0**2
        by_corners = near_field_terms(plan, amps, alpha, alpha, 96, ratio=ratio)
        by_quads = quadrant_terms(plan, fresnel_kernel, amps, alpha, 96, alpha)
    scale = max(float(np.max(np.abs(t))) for t in by_quads)
    for got, want in zip(by_corners, by_quads, strict=True):
        assert np.max(np.abs(np.asarray(got) - np.asarray(want))) < 1e-12 * scale


def test_lattice_table_is_used_at_its_ratio_only(monkeypatch):
    """With the lattice's evaluation spoilt on purpose (its Fresnel integrals doubled), the
    field changes where the lattice is used (its ratio, within float32 rounding) and not
    where the call's ratio has moved from it (a changed distance: the whole table), under
    jit and under vmap over distances (both branches run there)."""
    from invglare.optics.quad import nearfield

    evaluate = nearfield.fresnel_e
    spoilt = lambda s: evaluate(s) * (2.0 if s.ndim == 1 else 1.0)  # noqa: E731
    monkeypatch.setattr(nearfield, "fresnel_e", spoilt)
    plan, raster, step, alpha, _ = _square_near_setup(5, 1.0)
    field = jnp.asarray(raster, jnp.float32)
    run = jax.jit(lambda st, al, ratio: quad_near_field(plan, field, st, al, 101, ratio=ratio),
                  static_argnums=2)  # fmt: skip

    def differs(st, al):
        a, b = np.asarray(run(st, al, 1.0)), np.asarray(run(st, al, None))
        return np.max(np.abs(a - b)) / b.max()

    step32, alpha32 = jnp.float32(step), jnp.float32(alpha)
    assert differs(step32, alpha32) > 0.1  # the spoilt lattice is used
    ulp = float(jnp.finfo(jnp.float32).eps)
    assert differs(step32 * (1 + 3 * ulp), alpha32) > 0.1  # a ratio rounded off by 3 ulp
    assert differs(step32 * (1 + 100 * ulp), alpha32) < 1e-6  # 100 ulp: another ratio
    assert differs(step32, alpha32 * 1.01) < 1e-6  # moved: the whole table
    alphas = jnp.asarray([alpha, 1.01 * alpha], jnp.float32)
    many = jax.vmap(lambda al: run(step32, al, 1.0))(alphas)
    whole = jax.vmap(lambda al: run(step32, al, None))(alphas)
    rel = np.max(np.abs(np.asarray(many - whole)), axis=(1, 2)) / np.asarray(whole).max()
    assert rel[0] > 0.1 and rel[1] < 1e-6


def test_lattice_table_gradients_are_the_whole_tables():
    """float64, the 64 px heptagon on its own grid: the gradient with respect to the chirp
    (the distance), the output pixel and a soft edge pixel through the lattice table equals
    the whole table's to 1e-10 and converging central differences (whose steps leave the
    lattice's ratio, so they evaluate the whole table)."""
    with x64():
        raster = jnp.asarray(paper_raster("heptagon", 64))
        plan = _plan(raster, symmetric=False)
        edge = tuple(int(v) for v in np.argwhere((raster > 0.2) & (raster < 0.8))[0])
        alpha0 = 4.0 * 10.0 / 60.0**2
        w = jnp.asarray(np.random.default_rng(1).random((64, 64)))

        def loss(args, ratio):
            alpha, step, value = args
            psf = quad_near_field(plan, raster.at[edge].set(value), step, alpha, 64, ratio=ratio)
            return jnp.sum(w * psf)

        x0 = (alpha0, alpha0, raster[edge])  # step = alpha: ratio 1
        lattice = jax.jit(jax.grad(lambda a: loss(a, 1.0)))(x0)
        whole = jax.jit(jax.grad(lambda a: loss(a, None)))(x0)
        np.testing.assert_allclose(np.asarray(lattice), np.asarray(whole), rtol=1e-10)
        f = jax.jit(lambda a: loss(a, 1.0))
        for i in range(3):
            h = 1e-6 * abs(float(x0[i]))
            up = list(x0)
            down = list(x0)
            up[i], down[i] = x0[i] + h, x0[i] - h
            fd = (f(tuple(up)) - f(tuple(down))) / (2 * h)
            np.testing.assert_allclose(float(lattice[i]), float(fd), rtol=1e-6)


# ------------------------------------------------------------------------------ culling


@pytest.mark.slow
def test_culling_is_skipped_where_its_runs_would_cover_most_of_the_quadrant():
    """The culled evaluation computes the kept tiles' runs (gaps bridged), not the tiles:
    a heptagon whose 63 % kept tiles span 93 % of the quadrant and a box whose 27 % span
    56 % are evaluated dense; a box whose 15 % span 31 % is culled, with the forced tiles."""
    cases = [("heptagon", 256, 2 / 256, False), ("box", 256, 2 / 256, False),
             ("box", 512, 1 / 512, True)]  # fmt: skip
    for name, npix, step, culled in cases:
        raster = jnp.asarray(paper_raster(name, 128), jnp.float32)
        plan = _plan(raster)
        amps = np.asarray(plan_amplitudes(plan, raster)[0])
        args = (plan, box_kernel, amps, (step,), npix, 1e-5)
        forced = cull_tiles(*args, far=True, max_evaluated=1.0)
        tiles = cull_tiles(*args, far=True)
        share, kept = evaluated_fraction(forced, npix), kept_fraction(forced, npix)
        assert (share <= MAX_EVALUATED) == culled and kept < share, (name, npix, kept, share)
        if culled:
            np.testing.assert_array_equal(tiles.rows, forced.rows)
            np.testing.assert_array_equal(tiles.cols, forced.cols)
        else:
            assert tiles is None, (name, npix, kept, share)


@pytest.mark.slow
def test_culling_loses_no_more_than_its_threshold_and_keeps_gradients_exact():
    """Heptagon, 128 px raster to a 256 px output reaching its Nyquist angle, culled at
    1e-5 of the peak: 63 % of the tiles kept (forced: their runs span 93 % of the quadrant,
    where the dense evaluation is faster), the culled pixels hold less than that
    (measured 7e-7), and the gradient of a weighted loss with respect to the raster is the
    unculled one (the culled value's derivative is exact)."""
    n, npix, step = 128, 256, 2 / 256
    raster = jnp.asarray(paper_raster("heptagon", n), jnp.float32)
    plan = _plan(raster)
    amps, _ = plan_amplitudes(plan, raster)
    tiles = cull_tiles(
        plan, box_kernel, np.asarray(amps), (step,), npix, 1e-5, far=True, max_evaluated=1.0
    )
    assert tiles is not None and tiles.rows.size < 0.7 * (npix // 2 // 8 + 1) ** 2
    full = quad_far_field(plan, raster, step, npix)
    culled = quad_far_field(plan, raster, step, npix, tiles)
    err = culling_error(full, culled)
    assert err["max_error_over_peak"] < 1e-5
    weights = jnp.asarray(np.random.default_rng(0).random((npix, npix)), jnp.float32)

    def loss(r, t):
        return jnp.sum(weights * quad_far_field(plan, r, step, npix, t))

    g_full = jax.grad(loss)(raster, None)
    g_cull = jax.grad(loss)(raster, tiles)
    np.testing.assert_allclose(g_cull, g_full, rtol=1e-5, atol=1e-6 * float(jnp.abs(g_full).max()))
