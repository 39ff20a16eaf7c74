import gc
import os
import sys

import pytest

# Tests run on the CPU with float32 by default; float64 is enabled locally with helpers.x64().
os.environ.setdefault("JAX_PLATFORMS", "cpu")

# JAX's persistent compilation cache is off unless INVGLARE_JAX_CACHE names a folder. It
# saved about a quarter of the suite's compile time (shared by the xdist workers), but in two
# full-suite runs an xdist worker died of a segfault inside XLA's executable
# (de)serialisation (compilation_cache.get_executable_and_time / put_executable_and_time),
# each time in a test that passes alone: a lost worker costs the run.
_cache = os.environ.get("INVGLARE_JAX_CACHE", "")
if _cache:
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", _cache)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.3")


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module.

    Every compiled CPU program keeps about six memory maps; an xdist worker that compiles
    through most of the suite reaches the kernel's limit (vm.max_map_count, 65530 here), and
    the next compile dies of a segfault inside XLA instead of an error (seen late in three
    full-suite runs, each time in a test that passes alone).
    """
    yield
    jax = sys.modules.get("jax")
    if jax is not None:
        jax.clear_caches()
        gc.collect()
