"""invglare._core.allocator: freed memory stays in the heap instead of being paged in anew."""

from __future__ import annotations

import subprocess
import sys

import pytest

from invglare._core import allocator

# Allocates, touches and frees 64 MiB twice with the C library's malloc; prints the page
# faults of the second round (64 MiB is 16384 pages of 4 KiB).
_SCRIPT = """
import ctypes, resource, sys
import invglare._core.allocator
if sys.argv[1] == "on":
    assert invglare._core.allocator.retain_freed_memory()
libc = ctypes.CDLL(None)
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
size = 64 << 20
def round_trip():
    p = libc.malloc(size)
    ctypes.memset(p, 1, size)
    libc.free(p)
round_trip()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
round_trip()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str) -> int:
    out = subprocess.run(
        [sys.executable, "-c", _SCRIPT, mode], capture_output=True, text=True, check=True
    )
    return int(out.stdout.split()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt is Linux's")
def test_freed_memory_is_reused_without_page_faults():
    """By default glibc maps a 64 MiB block afresh (16384 faults); retained, it faults < 100."""
    assert _faults("off") > 8000
    assert _faults("on") < 100


def test_opt_out_by_environment(monkeypatch):
    monkeypatch.setenv(allocator.ENV_VAR, "default")
    assert allocator.retain_freed_memory() is False


def test_the_command_retains_freed_memory(monkeypatch):
    from typer.testing import CliRunner

    from invglare import cli

    calls = []
    monkeypatch.setattr(cli, "retain_freed_memory", lambda: calls.append(1) or True)
    result = CliRunner().invoke(cli.app, ["psf", "--help"])
    assert result.exit_code == 0
    assert calls == [1]
