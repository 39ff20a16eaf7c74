"""The quad and polygon propagation methods through the propagator abstraction, the models,
the configs; and every bad input they refuse."""

from __future__ import annotations

import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from invglare.aperture import Aperture, Capsule, Disk, ImageMask, RegularPolygon
from invglare.aperture.camera import CameraAperture, Diaphragm
from invglare.config.model import build_model
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.models.aperture_psf import AperturePSF
from invglare.models.kakimoto import KakimotoGlare
from invglare.optics.propagator import (
    PolygonFraunhofer,
    QuadFraunhofer,
    QuadFresnel,
    make_propagator,
)
from invglare.optics.quad.apertures import paper_grid, paper_raster
from invglare.optics.quad.options import QuadOptions
from invglare.optics.spectral import near_field_heuristic_factors, scaled_copies, xyz_to_rgb

HEPTAGON = Aperture((RegularPolygon(7, 3.6, rotation_deg=3.0),))


def _build(method, aperture=HEPTAGON, **kwargs):
    args = dict(
        focal_length_mm=17.0, npix=48, pixel_scale_deg=0.0016, aperture_npix=48, window_mm=4.0
    )
    args.update(kwargs)
    return AperturePSF.build(aperture, method=method, **args)


@pytest.mark.slow
def test_quad_model_equals_the_mft_model_times_the_pixel_transfer_under_jit_and_vmap():
    mft, quad = _build("mft"), _build("quad")
    assert isinstance(quad.propagator, QuadFraunhofer) and quad.propagator.plan is not None
    a, b = np.asarray(jax.jit(lambda m: m())(mft)), np.asarray(jax.jit(lambda m: m())(quad))
    out = quad.propagator.output
    f = np.asarray(out.coords_rad()) * float(quad.propagator.grid.pitch_mm) / 550e-6
    transfer = (np.sinc(f)[:, None] * np.sinc(f)[None, :]) ** 2
    assert np.max(np.abs(b - a * transfer)) < 1e-5 * a.max()
    # vmap over wavelengths (the propagator's own calls) and over models' leaves.
    lams = jnp.asarray([500.0, 600.0])
    many = jax.vmap(lambda lam: quad.propagator(quad.transmission(), lam))(lams)
    one = quad.propagator(quad.transmission(), 600.0)
    np.testing.assert_allclose(many[1], one, rtol=1e-5, atol=1e-7 * float(one.max()))


def test_polygon_model_is_alias_free_at_any_sampling():
    """The polygon path at a pixel scale no raster of 48 px could reach without aliasing
    (the MFT refuses it), against the exact closed form of the same polygon."""
    from invglare.reference.closed_forms import polygon_far_field

    fine = _build("polygon", pixel_scale_deg=0.02, npix=33)
    psf = np.asarray(jax.jit(lambda m: m())(fine))
    with pytest.raises(PhysicsRangeError, match="aliasing"):
        _build("mft", pixel_scale_deg=0.02, npix=33)
    out = fine.propagator.output
    theta = np.asarray(out.coords_rad())
    angle = np.radians(3.0) + 2 * np.pi * np.arange(7) / 7
    verts = 1.8 * np.stack([np.cos(angle), np.sin(angle)], -1)
    ref = np.asarray(polygon_far_field(theta[None, :], theta[:, None], verts, 550.0))
    ref = ref * float(out.solid_angle_sr())
    assert np.max(np.abs(psf - ref)) < 1e-5 * ref.max()


def test_fresnel_quad_model_needs_no_chirp_sampling():
    """At a distance whose chirp a 48 px raster cannot resolve (20 mm), fresnel + mft is
    refused (it would alias) and fresnel + quad is computed by Fresnel integrals: finite,
    the energy in a field holding the shadow within 3 % of 1 (the pattern's fine fringes
    between pixel samples). Where the chirp is well resolved (20 m: 0.1 rad per pixel at
    the window's edge) it is the chirp-sampled MFT times the pixel transfer, up to what a
    point sample of the chirp misses over a pixel (measured 3e-4 of the peak; 2 % at 2 m,
    1 rad per pixel)."""
    with pytest.raises(PhysicsRangeError, match="Fresnel phase"):
        _build("mft", propagation="fresnel", focal_length_mm=20.0)
    model = _build("quad", propagation="fresnel", focal_length_mm=20.0, npix=160,
                   pixel_scale_deg=0.08)  # fmt: skip
    assert isinstance(model.propagator, QuadFresnel)
    psf = np.asarray(jax.jit(lambda m: m())(model))
    assert np.all(np.isfinite(psf)) and 0.97 < psf.sum() < 1.03
    far = {m: _build(m, propagation="fresnel", focal_length_mm=2e4) for m in ("mft", "quad")}
    a, b = np.asarray(far["mft"]()), np.asarray(far["quad"]())
    out = far["quad"].propagator.output
    f = np.asarray(out.coords_rad()) * float(far["quad"].propagator.grid.pitch_mm) / 550e-6
    transfer = (np.sinc(f)[:, None] * np.sinc(f)[None, :]) ** 2
    assert np.max(np.abs(b - a * transfer)) < 1e-3 * a.max()


def test_fresnel_quad_on_its_own_grid_prepares_the_lattice_table():
    """Observed on the raster's own grid (output pixel = raster pitch at the distance) the
    prepared near field finds the ratio 1 and evaluates its Fresnel integrals by the lattice
    table, to the whole table's field within float32 rounding (1e-5 of the peak); at
    another pixel scale there is no lattice."""
    import dataclasses

    grid, d = paper_grid(64), 600.0

    def prop(scale):
        return make_propagator(
            window_mm=float(grid.width_mm), focal_length_mm=d, fft_wavelength_nm=550.0,
            shortest_wavelength_nm=550.0, npix=64, pixel_scale_deg=scale, aperture_npix=64,
            propagation="fresnel", method="quad",
        )  # fmt: skip

    raster = jnp.asarray(paper_raster("whirl", 64), jnp.float32)
    own = math.degrees(float(grid.pitch_mm) / d)
    ready = prop(own).prepared(raster)
    assert isinstance(ready, QuadFresnel) and ready.ratio == 1.0
    assert prop(0.37 * own).prepared(raster).ratio is None
    run = jax.jit(lambda p, f: p(f, 550.0))
    a = np.asarray(run(ready, raster))
    b = np.asarray(run(dataclasses.replace(ready, ratio=None), raster))
    assert np.max(np.abs(a - b)) < 1e-5 * b.max()


def test_near_field_heuristic_is_a_named_spectral_approximation():
    """Scandolo et al.'s near-field spectral heuristic (sec. 4.5, fig. 7): copies of the
    reference PSF magnified by ``1 / (1 + 0.05 (1 - lambda_r / lambda))``. It evaluates one
    wavelength; at a Fresnel number of about 10 its image is much nearer the exact
    per-wavelength sum than the far-field scaling (L1 errors measured here 0.10 against
    0.44 of the image; asserted: below half) and nearer than unscaled copies (0.11). It is
    refused for
    far-field propagation, where ``spectral = "scaled"`` is exact."""
    ref = 529.0
    factors = np.asarray(near_field_heuristic_factors(jnp.asarray([400.0, ref, 700.0]), ref))
    np.testing.assert_allclose(factors, 1 / (1 + 0.05 * (1 - ref / np.array([400, ref, 700]))))
    assert factors[0] > 1 > factors[2] and abs(factors[0] - 1) < 0.06 * abs(ref / 400 - 1)
    # a = 1.8 mm, d = 600 mm: Fresnel number a^2 / (lambda d) = 9.8 at 550 nm.
    images = {}
    for spectral in ("exact", "scaled", "near_field_heuristic"):
        model = _build("quad", propagation="fresnel", focal_length_mm=600.0, npix=96,
                       pixel_scale_deg=0.0045, aperture_npix=48, wavelengths_nm="400:700:8",
                       spectral=spectral, reference_wavelength_nm=ref)  # fmt: skip
        images[spectral] = np.asarray(jax.jit(lambda m: m())(model))
        if spectral == "exact":
            unscaled = model.propagator(model.transmission(), ref)  # copies at magnification 1
            ones = jnp.ones_like(model.spectrum.wavelengths_nm)
            xyz = jnp.moveaxis(scaled_copies(unscaled, ones, model.spectrum.weights_xyz), 0, -1)
            images["unscaled"] = np.asarray(xyz_to_rgb(xyz, "sRGB"))
        else:
            assert model.spectrum.computed_wavelengths_nm == (ref,)
            assert model.to_config()["spectrum"]["spectral"] == spectral
    exact = images["exact"]
    err = {k: np.abs(images[k] - exact).sum() / exact.sum() for k in images if k != "exact"}
    assert err["near_field_heuristic"] < min(0.5 * err["scaled"], 0.95 * err["unscaled"]), err
    with pytest.raises(ConfigError, match="near_field_heuristic"):
        _build("quad", wavelengths_nm="400:700:8", spectral="near_field_heuristic")


def test_kakimoto_camera_with_the_quad_method():
    camera = CameraAperture(Diaphragm(6, 8.0, 30.0, rotation_deg=4.0))
    kw = dict(focal_length_mm=30.0, obstacle_distance_mm=0.0, npix=48, pixel_scale_deg=0.005,
              aperture_npix=48, colour="spectral", wavelengths_nm=550.0)  # fmt: skip
    quad = KakimotoGlare.build(camera, method="quad", **kw)
    mft = KakimotoGlare.build(camera, method="mft", **kw)
    a, b = np.asarray(mft()), np.asarray(quad())
    assert np.max(np.abs(a - b)) < 0.02 * a.max()  # the pixel transfer only
    with pytest.raises(ConfigError, match="polygon"):
        KakimotoGlare.build(camera, method="polygon", **kw)
    with pytest.raises(ConfigError, match="masking = 'position'"):
        KakimotoGlare.build(camera, method="quad", masking="position", **kw)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["quad", "polygon"])
def test_config_round_trip_with_method_options(method):
    table = {"quad": {"cull_below": 1e-6, "base_level": 0}, "polygon": {"arc_segments": 8}}
    config = {
        "model": {
            "kind": "aperture",
            "focal_length_mm": 17.0,
            "aperture_npix": 48,
            "method": method,
            method: table[method],
            "shapes": [{"kind": "polygon", "n_blades": 6, "diameter_mm": 3.0, "rounding": 0.3}],
        },
        "output": {"npix": 32},
    }
    model = build_model(config)
    again = build_model(model.to_config())
    assert again.to_config() == model.to_config()
    assert model.to_config()["model"][method] == model.propagator.options()
    np.testing.assert_allclose(np.asarray(again()), np.asarray(model()), rtol=1e-6, atol=1e-9)
    other = "polygon" if method == "quad" else "quad"
    bad = {**config, "model": {**config["model"], other: {}}}
    with pytest.raises(ConfigError, match=f"model.{other}"):
        build_model(bad)
    typo = {**config, "model": {**config["model"], method: {"typo": 1}}}
    with pytest.raises(ConfigError, match="typo"):
        build_model(typo)


@pytest.mark.slow
def test_polygon_pieces_of_every_analytic_shape():
    """A rounded hexagon, a capsule across it (the part outside is the overlap residue) and
    a disk inside it (counted twice by the sum of transforms: the residue takes it off)
    through the polygon method against the quad method of the raster, both per unit power
    through the aperture (the polygon's F(0), the shapes' open area; the quads' sum |t|,
    the raster's own, which measures that area though its grey edges diffract only c²):
    measured 1.1e-3 of the peak, the raster's own approximation of the shapes."""
    aperture = Aperture(
        (RegularPolygon(6, 3.4, rounding=0.5), Capsule((-2.0, 0.3), (2.0, 0.6), 0.15), Disk(0.6))
    )
    poly = _build("polygon", aperture, window_mm=4.4, npix=40, pixel_scale_deg=0.003)
    assert poly.propagator.overlap is not None
    quad = _build("quad", aperture, window_mm=4.4, npix=40, pixel_scale_deg=0.003)
    a, b = np.asarray(poly()), np.asarray(quad())
    assert np.max(np.abs(a - b)) < 3e-3 * a.max()


# ---------------------------------------------------------------------------- bad input


def _prop(**kwargs):
    args = dict(window_mm=4.0, focal_length_mm=17.0, fft_wavelength_nm=550.0,
                shortest_wavelength_nm=550.0, npix=32, aperture_npix=32, method="quad")  # fmt: skip
    args.update(kwargs)
    return make_propagator(**args)


def test_bad_inputs_are_refused_with_the_reason():
    # An empty aperture.
    with pytest.raises(InputDataError, match="empty"):
        _prop().prepared(jnp.zeros((32, 32)))
    # A distance <= 0.
    with pytest.raises(PhysicsRangeError, match="focal_length_mm"):
        _prop(propagation="fresnel", focal_length_mm=0.0)
    # A sampling the closed form cannot carry in float32.
    with pytest.raises(PhysicsRangeError, match="cannot be represented"):
        _prop(npix=4096, pixel_scale_deg=2.0)
    # Polygons have no closed-form Fresnel integral.
    with pytest.raises(ConfigError, match="Fraunhofer"):
        _prop(method="polygon", propagation="fresnel")
    # Options of another method, unknown options, bad values.
    with pytest.raises(ConfigError, match="takes no options"):
        _prop(method="mft", pixel_scale_deg=0.001, method_options={"band": 1})
    with pytest.raises(ConfigError, match="unknown"):
        _prop(method_options={"bands": 1})
    with pytest.raises(PhysicsRangeError, match="cull_below"):
        QuadOptions(cull_below=2.0)
    # A traced raster the quadtree was not decided on; a complex field.
    unprepared = _prop()
    with pytest.raises(ConfigError, match="prepared"):
        jax.jit(lambda r: unprepared(r, 550.0))(jnp.ones((32, 32)))
    with pytest.raises(InputDataError, match="complex"):
        _prop().prepared(jnp.ones((32, 32)) * (1 + 1j))
    # An image shape has no vertices.
    image = Aperture((ImageMask.from_array(np.ones((8, 8)), 2.5),))
    with pytest.raises(ConfigError, match="image shape"):
        _build("polygon", image)
    assert isinstance(_prop(method="polygon"), PolygonFraunhofer)


def test_a_raster_departing_from_its_quadtree_is_a_runtime_error():
    """A fit that moves an edge beyond the band would get a wrong transform: refused."""
    model = _build("quad")
    moved = eqx.tree_at(lambda m: m.aperture.shapes[0].diameter_mm, model, 3.0)
    with pytest.raises(Exception, match="not the one its quadtree was decided on"):
        jax.block_until_ready(jax.jit(lambda m: m())(moved))
    # Within the band (a tiny change of the edges' coverage) it is fine.
    small = eqx.tree_at(lambda m: m.aperture.shapes[0].diameter_mm, model, 3.6 + 1e-4)
    assert np.all(np.isfinite(np.asarray(jax.jit(lambda m: m())(small))))


def test_non_power_of_two_aperture_raster_is_padded_and_says_so():
    model = _build("quad", aperture_npix=40, window_mm=4.0)
    assert "not a power of two" in model.propagator.plan.layout.note
    ref = _build("mft", aperture_npix=40, window_mm=4.0)
    out = model.propagator.output
    f = np.asarray(out.coords_rad()) * float(model.propagator.grid.pitch_mm) / 550e-6
    transfer = (np.sinc(f)[:, None] * np.sinc(f)[None, :]) ** 2
    a = np.asarray(ref())
    assert np.max(np.abs(np.asarray(model()) - a * transfer)) < 1e-5 * a.max()


def test_mft_refuses_what_quad_computes_at_the_same_raster():
    """The MFT of a 48 px raster reaches only its Nyquist angle; the quads go to twice it
    (192 pixels of the FFT's own scale) with the pixel boxes' sinc envelope, not a periodic
    replica: the energy there is between that within the band and the whole plane's. Per
    unit power through the heptagon (its area), the whole plane holds the raster's
    ``sum t^2 pitch^2 / area`` (0.9831: grey edges pass c but diffract c^2); measured
    0.9932 and 0.9962 of it in the band and twice it."""
    pixel_deg = math.degrees(550e-6 / (2 * 48 * 4.0 / 48))
    with pytest.raises(PhysicsRangeError, match="aliasing"):
        _build("mft", npix=192, pixel_scale_deg=pixel_deg)
    narrow = _build("quad", npix=96, pixel_scale_deg=pixel_deg)
    band = np.asarray(narrow()).sum()
    wide = np.asarray(_build("quad", npix=192, pixel_scale_deg=pixel_deg)()).sum()
    t, pitch = np.asarray(narrow.transmission()), float(narrow.propagator.grid.pitch_mm)
    whole = (t * t).sum() * pitch**2 / float(HEPTAGON.open_area_mm2())
    assert 0.98 * whole < band < wide <= whole


@pytest.mark.slow
def test_a_culled_propagator_holds_its_tiles_as_plain_integers():
    """Culling kept tiles (a box, 128 px to 512): they sit in a static field, as Python
    ints: numpy or JAX scalars there are arrays to equinox, which warned on every build."""
    grid = paper_grid(128)
    prop = make_propagator(
        window_mm=float(grid.width_mm), focal_length_mm=17.0, fft_wavelength_nm=550.0,
        shortest_wavelength_nm=550.0, npix=512, aperture_npix=128, method="quad",
        method_options={"cull_below": 1e-5},
    )  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        prepared = prop.prepared(jnp.asarray(paper_raster("box", 128)))
    size, rows, cols = prepared.tiles
    assert 0 < len(rows) == len(cols) < (512 // 2 // size + 1) ** 2
    assert all(type(i) is int for i in (size, *rows, *cols))
