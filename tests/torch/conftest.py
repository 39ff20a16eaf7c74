import jax
import pytest


@pytest.fixture(autouse=True)
def _no_persistent_cache_reads():
    """Torch tests compile afresh instead of loading the shared persistent cache.

    In a full-suite run an xdist worker crashed with a segfault inside XLA's executable
    deserialisation (``compilation_cache.get_executable_and_time``) while
    gradcheck's backward pass, run through torch's autograd, loaded a cached program; the
    same test passes alone and from a warm cache. Compiling these small programs costs
    seconds, a lost worker costs the run.
    """
    before = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    yield
    jax.config.update("jax_enable_compilation_cache", before)
