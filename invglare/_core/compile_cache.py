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
per compiled program. It is installed when :mod:`invglare._core` is imported.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from jax._src import lru_cache

_original_put = lru_cache.LRUCache.put


def _atomic_put(self: lru_cache.LRUCache, key: str, value: bytes) -> None:
    # With a size limit JAX holds a file lock around every read and write: already safe.
    if self.eviction_enabled or not isinstance(self.path, Path) or not key:
        _original_put(self, key, value)
        return
    final = self.path / f"{key}{lru_cache._CACHE_SUFFIX}"
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


def make_cache_writes_atomic() -> None:
    """Make JAX's compilation-cache writes atomic in this process (idempotent)."""
    lru_cache.LRUCache.put = _atomic_put  # type: ignore[method-assign]


def cache_writes_are_atomic() -> bool:
    """Whether :func:`make_cache_writes_atomic` is in effect in this process."""
    return lru_cache.LRUCache.put is _atomic_put
