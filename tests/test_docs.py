"""The docs site's API pages name modules that exist (a moved module breaks the strict build)."""

import importlib.util
import re
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"
DIRECTIVES = sorted(
    {
        (page.relative_to(DOCS).as_posix(), m.group(1))
        for page in DOCS.rglob("*.md")
        for m in re.finditer(r"^::: ([\w.]+)\s*$", page.read_text(encoding="utf-8"), re.M)
    }
)


def test_the_api_pages_name_modules():
    assert len(DIRECTIVES) > 20


@pytest.mark.parametrize("page, module", DIRECTIVES, ids=[m for _, m in DIRECTIVES])
def test_every_api_directive_names_an_existing_module(page, module):
    # find_spec finds the module without running it (invglare.torch needs no torch here).
    assert importlib.util.find_spec(module) is not None, f"{page}: ::: {module}"
