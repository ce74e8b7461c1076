"""A griffe extension: evclock's docstrings use reST roles; the site renders Markdown.

``:class:`SimEventLoop``` and ``:func:`~evclock.clock``` become links to the API reference
when the name is documented there, and code otherwise (an optional cross-reference: an
undocumented or external target never breaks the strict build). A reST literal-block marker
(``text::`` before an indented block) becomes a plain colon. The docstrings themselves do not
change; only what the site shows.
"""

from __future__ import annotations

import html
import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:class|func|meth|attr|data|mod|exc|obj|const):`(?P<target>[^`]+)`")


def _resolve(obj: griffe.Object, target: str) -> str | None:
    """The path of ``target`` seen from ``obj``'s docstring, or None outside evclock."""
    package = obj.package
    candidates = [target]
    scope: Any = obj
    while scope is not None:
        candidates.append(f"{scope.path}.{target}")
        scope = scope.parent
    for candidate in candidates:
        if not candidate.startswith(package.path + ".") and candidate != package.path:
            continue
        try:
            found = package[candidate.removeprefix(package.path + ".")]
        except (KeyError, ValueError, griffe.AliasResolutionError, griffe.CyclicAliasError):
            continue
        if found is not None:
            # An imported name: link to where it is defined (the API pages register that).
            return str(found.target_path if found.is_alias else candidate)
    return None


def _rewrite(obj: griffe.Object, text: str) -> str:
    def replace(match: re.Match[str]) -> str:
        target = match["target"].strip()
        title, _, explicit = target.partition(" <")
        if explicit:
            target = explicit.rstrip(">")
        shown = title if explicit else target.lstrip("~")
        if target.startswith("~"):
            target = target[1:]
            shown = target.rsplit(".", 1)[-1]
        if target.startswith("."):
            target = target.lstrip(".")
        code = f"<code>{html.escape(shown)}</code>"
        path = _resolve(obj, target)
        if path is None:
            return code
        return f'<autoref identifier="{html.escape(path)}" optional>{code}</autoref>'

    text = ROLE.sub(replace, text)
    return re.sub(r"(\S)::\n", r"\1:\n", text)


class ReSTRoles(griffe.Extension):
    """Rewrite the roles of every docstring of the package once it is loaded."""

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        seen: set[int] = set()
        stack: list[Any] = [pkg]
        while stack:
            obj = stack.pop()
            if obj.is_alias or id(obj) in seen:
                continue
            seen.add(id(obj))
            if obj.docstring is not None:
                obj.docstring.value = _rewrite(obj, obj.docstring.value)
            stack.extend(obj.members.values())
