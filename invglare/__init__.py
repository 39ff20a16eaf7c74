"""invglare: differentiable inverse modelling of glare in JAX.

The package is organised in one-way tiers (see ``docs/architecture.md``; the order is
checked by ``tests/test_tiers.py``): ``_core`` (checks, grids and units) and ``files``
at the bottom, then ``dynamics``, ``aperture``, ``optics`` and ``models`` (every model
implements :class:`invglare.models.base.AbstractGlareModel`), then ``render``, ``fit``
and ``reference``, the config readers in ``config``, and the applications and the
``invglare`` command on top. Import from the subpackages, e.g.
``from invglare.models.aperture_psf import AperturePSF``.
"""

__version__ = "0.1.0"
