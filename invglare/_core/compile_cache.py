"""JAX's persistent compilation cache, safe to share between processes.

JAX writes a cache entry in place (`LRUCache.put`: ``path.write_bytes(value)``) and takes a
file lock only when the cache has a size limit. Without one, a process that reads an entry
while another is still writing it, or after a writer was killed mid-write, gets a truncated
executable, and deserialising that can crash the process instead of raising. invglare
shares one cache between processes: the workers of `invglare fit-batch`, and the test
suite's workers and the commands they start (some of them killed on purpose).

:func:`make_cache_writes_atomic` makes each write whole or absent: the entry is written to
a temporary file in the same folder and renamed into place. It changes nothing else
(same keys, same contents, same eviction when a size limit is set) and costs one rename
per compiled program (no fsync: a lost cache entry is only compiled again). It does not
call :func:`invglare.files.atomic.atomic_path`, invglare's atomic writer, because this
tier lies below ``files`` and must install the patch in every process that imports
invglare. Importing :mod:`invglare._core` installs it, at once if JAX is
loaded and otherwise when JAX loads (it does not load JAX itself).
"""

from __future__ import annotations

import contextlib
import importlib.abc
import importlib.util
import os
import sys
import tempfile
from pathlib import Path
from types import ModuleType
from typing import Any

#: JAX's module holding the cache's file store (loaded by ``import jax``).
_STORE = "jax._src.lru_cache"


def _atomic_put(self: Any, key: str, value: bytes) -> None:
    # With a size limit JAX holds a file lock around every read and write: already safe.
    if self.eviction_enabled or not isinstance(self.path, Path) or not key:
        self._invglare_original_put(key, value)
        return
    final = self.path / f"{key}{sys.modules[_STORE]._CACHE_SUFFIX}"
    if final.exists():
        return
    # The temporary name does not end in the cache's suffix, so no reader or eviction
    # scan ever sees it; a writer killed here leaves only this file behind.
    fd, tmp = tempfile.mkstemp(dir=self.path, prefix=".partial-", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(value)
        os.replace(tmp, final)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _patch(store: ModuleType) -> None:
    cache = store.LRUCache
    if cache.put is not _atomic_put:
        cache._invglare_original_put = cache.put
        cache.put = _atomic_put


class _PatchWhenLoaded(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds JAX's cache module the usual way, and patches it right after it runs."""

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> Any:
        if name != _STORE:
            return None
        sys.meta_path.remove(self)  # the other finders now find it, once
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:
            return spec
        self._loader = spec.loader
        spec.loader = self
        return spec

    def create_module(self, spec: Any) -> ModuleType | None:
        return self._loader.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        self._loader.exec_module(module)
        _patch(module)


def make_cache_writes_atomic() -> None:
    """Make JAX's compilation-cache writes atomic in this process (idempotent).

    Does not import JAX: with JAX not loaded yet, the patch is made when it loads, so the
    commands that must answer before JAX loads (``invglare --help``, config errors) stay
    fast.
    """
    if _STORE in sys.modules:
        _patch(sys.modules[_STORE])
    elif not any(isinstance(f, _PatchWhenLoaded) for f in sys.meta_path):
        sys.meta_path.insert(0, _PatchWhenLoaded())


def cache_writes_are_atomic() -> bool:
    """Whether JAX is loaded and its compilation-cache writes are atomic in this process."""
    store = sys.modules.get(_STORE)
    return store is not None and store.LRUCache.put is _atomic_put
