"""Gradients of the quad and polygon transforms against central finite differences (float64):
through the quads' intensities (the raster), through shape parameters on the quad path,
and through polygon vertices and the shapes' parameters on the polygon path."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_grad_converges, x64

from invglare.aperture import Aperture, Capsule, Disk, RegularPolygon
from invglare.models.aperture_psf import AperturePSF
from invglare.optics.quad import build_quadtree, make_plan, quad_far_field, quad_near_field
from invglare.optics.quad.apertures import paper_raster
from invglare.optics.quad.polygon import polygon_transform, series_points
from invglare.reference.closed_forms import regular_polygon_vertices

NPIX = 48


def _weights(n=NPIX, seed=0):
    return jnp.asarray(np.random.default_rng(seed).random((n, n)))


@pytest.mark.slow
def test_gradient_through_quad_intensities():
    """d loss / d(pixel value) for a fractional edge pixel (its own quad), an interior pixel
    (sharing the open value's intensity) and through the near field: autodiff equals
    converging central differences; the layout stays the one built on the raster."""
    with x64():
        raster = jnp.asarray(paper_raster("heptagon", 32))
        layout = build_quadtree(np.asarray(raster), band=1)
        plan = make_plan(layout)
        w = _weights()
        edge = tuple(int(v) for v in np.argwhere((raster > 0.2) & (raster < 0.8))[0])
        inside = (16, 16)
        for far in (True, False):

            def loss(value, i, j, far=far):
                r = raster.at[i, j].set(value)
                if far:
                    psf = quad_far_field(plan, r, 1 / NPIX, NPIX)
                else:
                    psf = quad_near_field(plan, r, 1 / NPIX, 0.02, NPIX)
                return jnp.sum(w * jnp.log(psf + 1e-6))

            # The pixel is an argument (traced): one program for its values and one for its
            # gradient serve both pixels, where a program per pixel compiled four.
            value, grad = jax.jit(loss), jax.jit(jax.grad(loss))
            for at in (edge, inside):
                i, j = (jnp.asarray(k) for k in at)
                x = float(raster[at])
                f = functools.partial(value, i=i, j=j)
                assert_grad_converges(f, x, 1e-4, grad=grad(jnp.float64(x), i, j))


@pytest.mark.parametrize("method", ["quad", "polygon"])
@pytest.mark.slow
def test_gradient_through_shape_parameters(method):
    """A heptagon's rotation (3 deg, off its symmetry) and diameter, through the quad
    propagator (edges move within its band of 2 px) and the polygon propagator (no raster):
    autodiff equals converging central differences."""
    with x64():
        model = AperturePSF.build(
            Aperture((RegularPolygon(7, 3.6, rotation_deg=3.0),)),
            focal_length_mm=17.0,
            npix=NPIX,
            pixel_scale_deg=0.0016,
            aperture_npix=48,
            window_mm=4.0,
            method=method,
            method_options={"band": 2} if method == "quad" else None,
        )
        w = _weights()

        # Both parameters are arguments of one program (each at its built value while the
        # other varies: the same losses as a program per parameter), and one gradient
        # program gives autodiff's value of both.
        @jax.jit
        def loss(rotation, diameter):
            def leaves(m):
                return m.aperture.shapes[0].rotation_deg, m.aperture.shapes[0].diameter_mm

            return jnp.sum(w * jnp.log(eqx.tree_at(leaves, model, (rotation, diameter))() + 1e-7))

        x0 = (jnp.float64(3.0), jnp.float64(3.6))
        grads = jax.jit(jax.grad(loss, argnums=(0, 1)))(*x0)
        for k in range(2):
            f = (lambda x: loss(x, x0[1])) if k == 0 else (lambda x: loss(x0[0], x))
            assert_grad_converges(f, float(x0[k]), 2e-5 * max(1.0, float(x0[k])), grad=grads[k])


def test_gradient_through_polygon_vertices():
    with x64():
        v = regular_polygon_vertices(5, 3.0, 12.0)
        f = jnp.linspace(-6.0, 6.0, 33)
        at = series_points(np.asarray(f), np.asarray(f), 1.0)
        w = _weights(33)
        for k, axis in ((1, 0), (3, 1)):

            @jax.jit
            def loss(x, k=k, axis=axis):
                ft = polygon_transform(v.at[k, axis].set(x), f, f, at)
                return jnp.sum(w * (ft.real**2 + ft.imag**2))

            assert_grad_converges(loss, float(v[k, axis]), 1e-5)


@pytest.mark.slow
def test_gradient_of_a_lash_angle_on_the_polygon_path():
    """A capsule (a lash) across a disk pupil: the part outside the pupil is the overlap
    residue's quads; the lash's end moves a fraction of a pixel, inside the band."""
    with x64():
        aperture = Aperture((Disk(3.0), Capsule((-1.8, 0.2), (1.8, 0.5), 0.12)))
        model = AperturePSF.build(
            aperture, focal_length_mm=17.0, npix=NPIX, pixel_scale_deg=0.002,
            aperture_npix=48, window_mm=4.2, method="polygon",
        )  # fmt: skip
        assert model.propagator.overlap is not None
        w = _weights()

        @jax.jit
        def loss(y):
            m = eqx.tree_at(lambda m: m.aperture.shapes[1].end_mm, model, jnp.array([1.8, y]))
            return jnp.sum(w * jnp.log(m() + 1e-7))

        assert_grad_converges(loss, 0.5, 1e-4)


def test_symmetric_fast_path_has_the_full_gradient():
    """At rotation 0 the heptagon is symmetric and the odd terms are skipped in the value;
    the gradient with respect to its raster is still that of the whole transform."""
    with x64():
        raster = jnp.asarray(paper_raster("heptagon", 32))
        layout = build_quadtree(np.asarray(raster))
        w = _weights()

        def grad(plan):
            return jax.grad(lambda r: jnp.sum(w * quad_far_field(plan, r, 1 / NPIX, NPIX)))(raster)

        full = grad(make_plan(layout))
        fast = grad(make_plan(layout, mirror_x=False, mirror_y=True))
    np.testing.assert_allclose(fast, full, rtol=1e-10, atol=1e-12 * float(jnp.abs(full).max()))
