"""A griffe extension for the docs build: Sphinx roles in docstrings shown as inline code.

Many docstrings of the package name other objects the Sphinx way (:func:`name`,
:class:`~pkg.Name`, :mod:`pkg.mod`). mkdocstrings renders docstrings as Markdown, where a
role would show as literal text (":func:" before the name); this extension rewrites each
role to the name in backticks (the last component for a ``~`` target, as Sphinx shows it)
before the page is rendered. The sources are not touched.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|data|attr|obj|exc|const):`(~?)([^`]+)`")


def plain(text: str) -> str:
    """`text` with every Sphinx role replaced by its target in backticks."""

    def repl(match: re.Match) -> str:
        tilde, target = match.groups()
        return f"`{target.rsplit('.', 1)[-1] if tilde else target}`"

    return _ROLE.sub(repl, text)


class SphinxRoles(griffe.Extension):
    """Rewrite Sphinx roles in every loaded object's docstring."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = plain(obj.docstring.value)
