import getpass
import os
import tempfile
from pathlib import Path

# Tests run on the CPU with float32 by default; float64 is enabled locally with helpers.x64().
os.environ.setdefault("JAX_PLATFORMS", "cpu")

# Many tests compile the same programs through fresh closures (a model built again, a new
# jitted loss), which JAX's in-memory cache cannot recognise; the persistent cache keys on
# the program itself, and is shared by the xdist workers. Measured on tests/test_fit.py and
# tests/models/test_kakimoto.py with 2 workers: 228 s without it, 190-207 s starting empty, 152 s
# on a second run (the cache stays in the temp folder).
# INVGLARE_JAX_CACHE= (empty) turns it off; a path puts it elsewhere.
_cache = os.environ.get(
    "INVGLARE_JAX_CACHE",
    str(Path(tempfile.gettempdir()) / f"invglare-jax-cache-{getpass.getuser()}"),
)
if _cache:
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", _cache)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.3")
