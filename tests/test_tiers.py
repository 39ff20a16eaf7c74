"""The package's tiers: no module imports from a tier above its own (also inside functions).

The order below is the one `docs/architecture.md` draws; it is written here once. Tiers
that list several subpackages hold siblings, which must not import each other either.
"""

from __future__ import annotations

import ast
import textwrap
from pathlib import Path

import pytest

import invglare

#: Low to high. A module may import from its own subpackage and from lower tiers only.
TIERS: tuple[tuple[str, ...], ...] = (
    ("errors",),
    ("_core",),
    ("files",),
    ("dynamics",),
    ("aperture",),
    ("optics",),
    ("models",),
    ("render", "fit", "reference"),
    ("config",),
    ("reports",),
    ("torch",),
    ("bench", "regress", "cie_study"),
    ("commands",),
    ("cli",),
)

PACKAGE_ROOT = Path(invglare.__file__).resolve().parent


def _tier_of(part: str) -> int | None:
    for i, names in enumerate(TIERS):
        if part in names:
            return i
    return None


def _module_name(path: Path, root: Path) -> str:
    rel = path.relative_to(root.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imported(node: ast.AST, module: str, is_package: bool) -> list[str]:
    """Absolute module names an import statement names (relative ones resolved)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if isinstance(node, ast.ImportFrom):
        if node.level:
            base = module.split(".")
            if not is_package:
                base = base[:-1]
            base = base[: len(base) - (node.level - 1)]
            prefix = ".".join(base + ([node.module] if node.module else []))
        else:
            prefix = node.module or ""
        # `from invglare import fit` names the subpackage through the alias;
        # `from invglare import __version__` names the package face, which imports nothing.
        if prefix == invglare.__name__:
            return [prefix if a.name.startswith("__") else f"{prefix}.{a.name}" for a in node.names]
        return [prefix]
    return []


def tier_violations(root: Path = PACKAGE_ROOT) -> list[str]:
    """Every import of a module under `root` that reaches a tier above (or a sibling)."""
    top = root.name
    problems = []
    for path in sorted(root.rglob("*.py")):
        module = _module_name(path, root)
        parts = module.split(".")
        if len(parts) < 2:
            continue  # the package face (invglare/__init__.py)
        own = parts[1]
        own_tier = _tier_of(own)
        if own_tier is None:
            problems.append(f"{module}: subpackage {own!r} has no tier in tests/test_tiers.py")
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            for name in _imported(node, module, path.name == "__init__.py"):
                target = name.split(".")
                if target[0] != top or len(target) < 2 or target[1] == own:
                    continue
                tier = _tier_of(target[1])
                if tier is None:
                    problems.append(f"{module}:{node.lineno} imports {name}: no such tier")
                elif tier > own_tier or (tier == own_tier and target[1] != own):
                    problems.append(
                        f"{module}:{node.lineno} imports {name} "
                        f"(tier {TIERS[tier]} is not below {TIERS[own_tier]})"
                    )
    return problems


def test_no_module_imports_from_above():
    assert tier_violations() == []


def _fake_package(tmp_path: Path, files: dict[str, str]) -> Path:
    root = tmp_path / invglare.__name__
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text), encoding="utf-8")
    return root


@pytest.mark.parametrize(
    "source, expected",
    [
        ("from invglare.fit.params import Parameter\n", "invglare.fit.params"),
        ("def f():\n    import invglare.config.model\n", "invglare.config.model"),
        ("from ..render import bright\n", "invglare.render"),
        ("from invglare import commands\n", "invglare.commands"),
    ],
)
def test_a_wrong_import_is_found(tmp_path, source, expected):
    root = _fake_package(
        tmp_path,
        {
            "__init__.py": "",
            "aperture/__init__.py": "",
            "aperture/wrong.py": source,
            "aperture/fine.py": "from invglare._core.checks import as_float\nfrom . import wrong\n",
        },
    )
    problems = tier_violations(root)
    assert len(problems) == 1, problems
    assert problems[0].startswith("invglare.aperture.wrong:") and expected in problems[0]


def test_siblings_do_not_import_each_other(tmp_path):
    root = _fake_package(
        tmp_path,
        {"__init__.py": "", "fit/__init__.py": "", "fit/x.py": "import invglare.render.bright\n"},
    )
    assert any("invglare.render.bright" in p for p in tier_violations(root))


def test_a_subpackage_without_a_tier_is_reported(tmp_path):
    root = _fake_package(tmp_path, {"__init__.py": "", "newthing/__init__.py": ""})
    assert tier_violations(root) == [
        "invglare.newthing: subpackage 'newthing' has no tier in tests/test_tiers.py"
    ]
