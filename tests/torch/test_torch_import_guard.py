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
        "import invglare.models, invglare.fit, invglare.render, invglare.io.model_config",
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


def test_without_torch_the_error_names_the_extra():
    # sys.modules["torch"] = None makes `import torch` fail as if it were not installed.
    code = (
        "import sys\nsys.modules['torch'] = None\n"
        "try:\n    import invglare.torch\nexcept ImportError as e:\n    print(e)\n"
        "import invglare.fit\nprint('core ok')"
    )
    out = _python(code)
    assert out.returncode == 0, out.stderr
    assert "pip install 'invglare[torch]'" in out.stdout
    assert out.stdout.strip().endswith("core ok")
