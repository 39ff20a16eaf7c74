"""The memory limit: parsed from INVGLARE_MEMORY_LIMIT or derived from the machine."""

from __future__ import annotations

import subprocess
import sys

import pytest

from invglare._core.memory import check_memory, memory_limit, parse_size
from invglare.errors import ConfigError, MemoryLimitError


@pytest.mark.parametrize(
    ("text", "nbytes"),
    [("3G", 3 * 1024**3), ("512MiB", 512 * 1024**2), ("1.5e9", 1_500_000_000), ("2 gb", 2 << 30)],
)
def test_sizes_are_parsed(text, nbytes):
    assert parse_size(text) == nbytes


@pytest.mark.parametrize("text", ["lots", "-1G", "0", "nanG", "3X"])
def test_bad_sizes_are_refused(text):
    with pytest.raises(ConfigError, match="INVGLARE_MEMORY_LIMIT"):
        parse_size(text)


def test_the_environment_sets_the_limit(monkeypatch):
    monkeypatch.setenv("INVGLARE_MEMORY_LIMIT", "1G")
    assert memory_limit() == (1024**3, "set by INVGLARE_MEMORY_LIMIT")
    check_memory(1024**3, "just fits")
    with pytest.raises(MemoryLimitError, match=r"\(--npix\) needs about 2\.0 GiB .* 1\.0 GiB"):
        check_memory(2 * 1024**3, "a raster (--npix)")
    monkeypatch.setenv("INVGLARE_MEMORY_LIMIT", "none")
    check_memory(1e30, "anything")


def test_the_derived_limit_follows_the_address_space_limit():
    """Under `ulimit -v`, the limit is 80 % of the room left below it."""
    code = (
        "import resource; resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30));"
        "from invglare._core.memory import memory_limit; print(*memory_limit(), sep='|')"
    )
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": ":".join(sys.path)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env=env).stdout.strip()  # fmt: skip
    limit, how = out.split("|")
    assert 0 < int(limit) < 0.8 * (3 << 30) and "address-space limit" in how
