"""The bottom tier: shared checks, grids and units, colour constants, gradient-safe maths
and XLA helpers.

Every other tier may import from here; nothing here imports from the rest of invglare
except :mod:`invglare.errors`.

Importing it makes JAX's compilation-cache writes atomic (:mod:`.compile_cache`): invglare's
processes share one cache.
"""

from invglare._core.compile_cache import make_cache_writes_atomic

make_cache_writes_atomic()
