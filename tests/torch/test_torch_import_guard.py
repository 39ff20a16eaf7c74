"""torch stays optional: the core never imports it, and invglare.torch says what to install."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _python(code: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300
    )


@pytest.mark.parametrize(
    "imports",
    [
        "import invglare",
        "import invglare.models, invglare.fit, invglare.render, invglare.config.model",
        "import invglare.bench.torch_cases",  # the bench cases import torch only when run
    ],
)
def test_core_imports_leave_torch_out(imports):
    out = _python(f"import sys\n{imports}\nprint('torch' in sys.modules)")
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def test_cli_help_leaves_torch_out():
    code = (
        "import sys\nfrom invglare.cli import main\nsys.argv = ['invglare', '--help']\n"
        "try:\n    main()\nexcept SystemExit as e:\n    assert e.code in (0, None), e.code\n"
        "print('TORCH', 'torch' in sys.modules)"
    )
    out = _python(code)
    assert out.returncode == 0, out.stderr
    assert "Usage" in out.stdout and out.stdout.strip().endswith("TORCH False")


_NO_TORCH = """
import importlib.abc, sys

class NoTorch(importlib.abc.MetaPathFinder):  # `import torch` fails as if not installed
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None

sys.meta_path.insert(0, NoTorch())
"""


def test_without_torch_the_error_names_the_extra():
    code = _NO_TORCH + (
        "try:\n    import invglare.torch\nexcept ImportError as e:\n    print(e)\n"
        "from invglare.files.toml import load_toml\n"
        "from invglare.config.model import build_model\n"
        f"model = build_model(load_toml({str(ROOT / 'examples' / 'circle.toml')!r}), npix=64)\n"
        "import numpy as np\npsf = np.asarray(model())\n"
        "assert psf.shape == (64, 64) and np.argmax(psf) == 32 * 64 + 32\nprint('core ok')"
    )
    out = _python(code)
    assert out.returncode == 0, out.stderr
    assert "pip install 'invglare[torch]'" in out.stdout
    assert out.stdout.strip().endswith("core ok")
