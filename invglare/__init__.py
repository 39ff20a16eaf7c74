"""invglare: differentiable inverse modelling of glare in JAX.

The package is organised in one-way tiers (see DESIGN.md): ``optics`` and
``aperture`` (pure functions and soft rasterisation) → ``models`` (forward
models as equinox Modules) → ``render``, ``fit`` and ``reference``; ``io`` and
the ``invglare`` command sit at the edge. Import from the subpackages, e.g.
``from invglare.models.aperture_psf import AperturePSF``.
"""

__version__ = "0.1.0"
