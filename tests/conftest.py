import gc
import os
import shutil
import sys
import tempfile

import pytest

# Tests run on the CPU with float32 by default; float64 is enabled locally with helpers.x64().
os.environ.setdefault("JAX_PLATFORMS", "cpu")

# JAX's persistent compilation cache is on, in a folder made for this run (fresh, as on a
# clean CI clone) and shared by the xdist workers and the commands the tests start, which
# inherit the environment: programs compiled by one are loaded by the others. On the 2-core
# machine it took tests/aperture's fast tests from 204 s to 174 s. INVGLARE_JAX_CACHE names
# another folder (kept between runs), or "off". Cache writes are atomic
# (invglare._core.compile_cache): a process killed mid-write, as the kill tests do, or
# a reader racing a writer never loads a truncated program. (Before they were, two full runs
# with a shared cache lost an xdist worker to a segfault in XLA's executable (de)serialisation.)
_cache = os.environ.get("INVGLARE_JAX_CACHE", "")
_made_cache = None
if not _cache:
    _cache = _made_cache = tempfile.mkdtemp(prefix="invglare-jax-cache-")
    os.environ["INVGLARE_JAX_CACHE"] = _cache  # the xdist workers use the same folder
if _cache != "off":
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", _cache)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")


#: The longest tests (minutes each under CI's two xdist workers, by ``--durations``), run
#: first, longest first: started last, one of them kept a worker busy for minutes after the
#: other had run out of tests.
_LONGEST_FIRST = (
    "tests/fit/test_other_draws.py::test_a_daylight_eye_the_model_did_not_draw",
    "tests/bench/test_bench.py::test_batch_benchmark_times_warm_clusters_of_1_and_2_workers",
    "tests/test_readme.py::test_readme_section_runs[Animated glare through a living eye "
    "(Ritschel et al.)]",
    "tests/test_readme.py::test_readme_section_runs[Many photos at once: invglare fit-batch]",
)


def pytest_collection_modifyitems(config, items):
    rank = {node: i for i, node in enumerate(_LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid, len(rank)))  # stable: the rest in order


def pytest_unconfigure(config):
    if _made_cache is not None:
        shutil.rmtree(_made_cache, ignore_errors=True)


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
