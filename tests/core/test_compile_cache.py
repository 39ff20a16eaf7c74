"""invglare._core.compile_cache: a compilation-cache entry is written whole or not at all."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from jax._src import lru_cache

from invglare._core import compile_cache


def _files(folder) -> list[str]:
    return sorted(os.listdir(folder))


def _printed(script: str, *args: str, env: dict | None = None) -> list[str]:
    """The words a fresh Python process prints running `script`."""
    done = subprocess.run([sys.executable, "-c", script, *args], capture_output=True, text=True,
                          check=True, timeout=120, env=env)  # fmt: skip
    return done.stdout.split()


def test_importing_invglare_makes_the_writes_atomic():
    script = (
        "import jax._src.lru_cache as c; before = c.LRUCache.put\n"
        "import invglare.models.aperture_psf\n"
        "from invglare._core.compile_cache import cache_writes_are_atomic\n"
        "print(before is c.LRUCache.put, cache_writes_are_atomic())"
    )
    assert _printed(script) == ["False", "True"]


def test_the_patch_waits_for_jax_to_load_and_does_not_load_it():
    script = (
        "import sys, invglare._core\n"
        "from invglare._core.compile_cache import cache_writes_are_atomic\n"
        "print('jax' in sys.modules, cache_writes_are_atomic())\n"
        "import jax\n"
        "print(cache_writes_are_atomic())"
    )
    assert _printed(script) == ["False", "False", "True"]


def test_an_entry_reads_back_and_leaves_no_partial_file(tmp_path):
    cache = lru_cache.LRUCache(str(tmp_path), max_size=-1)
    payload = os.urandom(1 << 16)
    cache.put("prog", payload)
    assert cache.get("prog") == payload
    assert _files(tmp_path) == ["prog-cache"]
    cache.put("prog", b"other")  # an existing entry is kept, as JAX does
    assert cache.get("prog") == payload


def test_a_writer_killed_mid_write_leaves_no_entry(tmp_path, monkeypatch):
    cache = lru_cache.LRUCache(str(tmp_path), max_size=-1)

    def dies(src, dst):
        assert os.path.getsize(src) == 4096  # the bytes are all in the temporary file
        raise KeyboardInterrupt

    monkeypatch.setattr(compile_cache.os, "replace", dies)
    with pytest.raises(KeyboardInterrupt):
        cache.put("prog", b"\1" * 4096)
    assert cache.get("prog") is None
    assert _files(tmp_path) == []


def test_a_size_limited_cache_keeps_jax_own_locked_writes(tmp_path):
    cache = lru_cache.LRUCache(str(tmp_path), max_size=1 << 20)
    cache.put("prog", b"abc")
    assert cache.get("prog") == b"abc"
    assert "prog-atime" in _files(tmp_path)  # JAX's own bookkeeping for eviction


def test_a_jitted_program_is_cached_and_loaded_by_another_process(tmp_path):
    script = (
        "import sys, jax, jax.numpy as jnp, invglare._core\n"
        "jax.config.update('jax_compilation_cache_dir', sys.argv[1])\n"
        "jax.config.update('jax_persistent_cache_min_compile_time_secs', 0)\n"
        "hits = []\n"
        "jax.monitoring.register_event_listener(\n"
        "    lambda name, **kw: hits.append(name) if name.endswith('cache_hits') else None)\n"
        "print(float(jax.jit(lambda x: jnp.sin(x) * 3)(1.0)), len(hits))"
    )
    folder = tmp_path / "cache"
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    runs = [_printed(script, str(folder), env=env) for _ in range(2)]
    (value, hits_first), (again, hits_second) = runs
    assert value == again and float(value) == pytest.approx(3 * 0.8414709848)
    assert int(hits_first) == 0 and int(hits_second) >= 1
    entries = _files(folder)
    assert any(name.endswith("-cache") for name in entries)
    assert not any(name.startswith(".partial-") for name in entries)
