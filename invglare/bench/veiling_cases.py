"""Per-size benchmark cases of the veiling-glare series against the ghost count.

Lee's point (sec. 4): once the ghosts are summed in coefficient space, the per-pixel cost
does not depend on how many there are. These cases time one veiling image of K = 10,
100 and 1000 random ghosts on an N x N screen of a fixed 40° field, with N_h = 64 and
256 harmonics (``veiling_K{K}_H{N_h}``), next to the same ghosts drawn directly
(``veiling_direct_K{K}``): each ghost's soft-edged disk evaluated at every pixel and
summed, ``O(K N²)``. The direct edge is a complementary error function across the rim
(a Gaussian-blurred half-plane: the blurred disk's edge for radii much larger than the
blur), the same cost class as the exact blurred disk.
"""

from __future__ import annotations

import numpy as np

from invglare.bench.cases import Case

GHOST_COUNTS = (10, 100, 1000)
HARMONICS = (64, 256)
#: The screen's field of view (deg): the same ghosts at every N.
FIELD_DEG = 40.0


def _ghost_arrays(k: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(k)
    return {
        "position_deg": rng.uniform(-15.0, 15.0, size=(k, 2)),
        "radius_deg": rng.uniform(1.0, 6.0, size=k),
        "intensity_per_sr": rng.uniform(1e-4, 1e-2, size=k),
        "softness_deg": rng.uniform(0.05, 0.3, size=k),
    }


def _series(k: int, n_harmonics: int):
    def make(n: int):
        import equinox as eqx

        from invglare.models.veiling import GhostSet, VeilingGlare

        a = _ghost_arrays(k)
        ghosts = GhostSet.build(
            a["position_deg"], a["radius_deg"], a["intensity_per_sr"],
            softness_deg=a["softness_deg"],
        )  # fmt: skip
        model = VeilingGlare.build(
            ghosts, npix=n, pixel_scale_deg=FIELD_DEG / n, n_harmonics=n_harmonics
        )
        image = eqx.filter_jit(lambda m: m())
        return lambda: image(model)

    return make


def _direct(k: int):
    def make(n: int):
        import jax
        import jax.numpy as jnp
        from jax.scipy.special import erfc

        a = {key: jnp.asarray(v, jnp.float32) for key, v in _ghost_arrays(k).items()}
        axis = (jnp.arange(n, dtype=jnp.float32) - n // 2) * (FIELD_DEG / n)

        @jax.jit
        def image(a):
            def add(acc, g):
                (px, py), radius, intensity, soft = g
                r = jnp.hypot(axis[None, :] - px, axis[:, None] - py)
                return acc + intensity * 0.5 * erfc((r - radius) / (jnp.sqrt(2.0) * soft)), None

            ghosts = (a["position_deg"], a["radius_deg"], a["intensity_per_sr"],
                      a["softness_deg"])  # fmt: skip
            out, _ = jax.lax.scan(add, jnp.zeros((n, n), jnp.float32), ghosts)
            return out

        return lambda: image(a)

    return make


VEILING_CASES: tuple[Case, ...] = (
    *(
        Case(
            f"veiling_K{k}_H{h}",
            "pipeline",
            f"VeilingGlare image of {k} random disk ghosts, {h} harmonics: coefficients "
            "aggregated in Fourier space, then the separable evaluation",
            _series(k, h),
        )
        for k in GHOST_COUNTS
        for h in HARMONICS
    ),
    *(
        Case(
            f"veiling_direct_K{k}",
            "pipeline",
            f"the same {k} ghosts drawn directly: a soft-edged disk per ghost at every pixel",
            _direct(k),
        )
        for k in GHOST_COUNTS
    ),
)

__all__ = ["FIELD_DEG", "GHOST_COUNTS", "HARMONICS", "VEILING_CASES"]
