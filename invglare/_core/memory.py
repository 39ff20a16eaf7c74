"""Memory budgets: sizes a user asks for are checked against the machine before allocating.

A raster of 65536² complex pixels is 32 GiB; asked for by mistake it swaps the machine or
gets the process killed with no message. Every user-controlled size (rasters, outputs,
wavelength counts, scenes, walkers, frames) is turned into an estimate of the bytes it
needs and compared with :func:`memory_limit` *before* the work starts; over the limit,
:func:`check_memory` raises a :class:`~invglare.errors.MemoryLimitError` giving both.

**The limit** is 80 % of what the process can still get: the smallest of the memory the
kernel reports available (``MemAvailable``), the room left under a cgroup's
``memory.max`` and under the address-space limit (``RLIMIT_AS``). The environment
variable ``INVGLARE_MEMORY_LIMIT`` sets it instead: bytes, or with a unit (``"8G"``,
``"512MiB"``), or ``"none"`` for no check.

**Example:**

```python
from invglare._core.memory import check_memory

check_memory(4 * 8 * 65536**2, "an aperture raster of 65536^2 complex pixels (aperture_npix)")
# MemoryLimitError: an aperture raster of ... needs about 128.0 GiB of memory; the limit is ...
```
"""

from __future__ import annotations

import math
import os
import re
import resource

from invglare.errors import ConfigError, MemoryLimitError

#: Environment variable that sets the limit (bytes, "8G", "512MiB", or "none").
ENV_VAR = "INVGLARE_MEMORY_LIMIT"
#: Share of the available memory the limit allows (the rest: Python, JAX, the OS).
AVAILABLE_SHARE = 0.8
GIB = 1024**3
_UNITS = {"": 1, "k": 1024, "m": 1024**2, "g": GIB, "t": 1024**4}
_SIZE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:e[+-]?\d+)?)\s*([kmgt]?)(?:i?b)?\s*$", re.IGNORECASE)


def parse_size(text: str, name: str = ENV_VAR) -> int:
    """Bytes of a size written ``"3G"``, ``"512MiB"``, ``"1.5e9"`` (a ConfigError if not)."""
    m = _SIZE.match(text)
    if m is None or not math.isfinite(float(m.group(1))) or float(m.group(1)) <= 0:
        raise ConfigError(
            f"{name} = {text!r} is not a size; write bytes or a number with a unit, e.g. 8G, "
            "512M, or 'none' for no limit"
        )
    return int(float(m.group(1)) * _UNITS[m.group(2).lower()])


def _meminfo_available() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _read_int(path: str) -> int | None:
    try:
        with open(path) as f:
            text = f.read().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _cgroup_room() -> int | None:
    """Room left under this process's cgroup memory limit (v2, else v1), if it has one."""
    try:
        with open("/proc/self/cgroup") as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        base = "/sys/fs/cgroup" + ("" if parts[0] == "0" else "/memory")
        if parts[0] != "0" and "memory" not in parts[1].split(","):
            continue
        folder = base + parts[2]
        v2 = parts[0] == "0"
        limit = _read_int(folder + ("/memory.max" if v2 else "/memory.limit_in_bytes"))
        used = _read_int(folder + ("/memory.current" if v2 else "/memory.usage_in_bytes"))
        if limit is not None and used is not None and limit < 2**60:
            return max(limit - used, 0)
    return None


def _address_space_room() -> int | None:
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        with open("/proc/self/statm") as f:
            size = int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:
        return None
    return max(soft - size, 0)


def memory_limit() -> tuple[int | None, str]:
    """``(bytes allowed for one allocation plan, how that limit was set)``; None: no limit."""
    text = os.environ.get(ENV_VAR, "").strip()
    if text.lower() == "none":
        return None, f"{ENV_VAR}=none"
    if text:
        return parse_size(text), f"set by {ENV_VAR}"
    rooms = {
        "available memory": _meminfo_available(),
        "the cgroup's memory limit": _cgroup_room(),
        "the address-space limit": _address_space_room(),
    }
    known = {k: v for k, v in rooms.items() if v is not None}
    if not known:
        return None, "unknown available memory"
    what, room = min(known.items(), key=lambda kv: kv[1])
    return int(AVAILABLE_SHARE * room), f"{AVAILABLE_SHARE:.0%} of {what}; set {ENV_VAR} to change"


def shown_bytes(n: float) -> str:
    """``"1.5 GiB"`` (GiB from 0.1 GiB up, MiB below)."""
    return f"{n / GIB:,.1f} GiB" if n >= 0.1 * GIB else f"{n / 1024**2:,.1f} MiB"


def check_memory(nbytes: float, what: str) -> None:
    """Raise :class:`~invglare.errors.MemoryLimitError` if `nbytes` exceed :func:`memory_limit`.

    **Arguments:**

    - `nbytes`: the estimate (a float: products of user sizes may exceed any integer type).
    - `what`: what needs it, naming the option or key that sets the size, e.g.
      ``"a PSF of 65536^2 pixels (--npix)"``.
    """
    limit, how = memory_limit()
    if limit is None or nbytes <= limit:
        return
    raise MemoryLimitError(
        f"{what} needs about {shown_bytes(nbytes)} of memory; the limit is "
        f"{shown_bytes(limit)} ({how})"
    )


def check_psf_memory(
    source: str, *, aperture_npix: int | None, npix: int | tuple[int, int], n_wavelengths: int,
    names: str,
) -> None:
    """Refuse a PSF model whose grids cannot fit, before it is built.

    A lower bound of what one evaluation holds at once: per wavelength, the complex
    aperture field (complex64, `aperture_npix`²) and the output image (float32, `npix`²).
    `names` says which keys set the sizes, for the message.
    """
    ny, nx = (npix, npix) if isinstance(npix, int) else npix
    field = 8.0 * float(aperture_npix or 0) ** 2
    need = float(n_wavelengths) * (field + 4.0 * float(ny) * float(nx))
    shown = f"{ny}x{nx} output pixels"
    if aperture_npix:
        shown = f"a {aperture_npix}^2 aperture raster and {shown}"
    check_memory(need, f"{source}: {shown} at {n_wavelengths} wavelength(s) ({names})")


def check_compiled_memory(compiled, what: str) -> None:
    """Refuse to run a compiled XLA program whose buffers (temporaries and outputs, as XLA
    plans them) exceed the limit. Programs without a memory analysis pass."""
    try:
        stats = compiled.memory_analysis()
    except (AttributeError, NotImplementedError, RuntimeError):
        return
    if stats is None:
        return
    check_memory(float(stats.temp_size_in_bytes) + float(stats.output_size_in_bytes), what)
