"""griffe extension (mkdocs.yml, mkdocstrings' python handler): lnf's docstrings cross-reference with Sphinx roles.

A docstring writes ``:meth:`reduce```, ``:class:`~lnf.trajectories.Trajectories``` or ``:func:`lnf.reduction.reduce```
as Sphinx (and an IDE) reads them; Markdown would print the role as it stands. Once griffe has loaded the package,
this extension rewrites every role of every docstring into inline code wrapped in an *optional* cross-reference of
mkdocs-autorefs: the name is resolved in the scope of the object whose docstring it is (its members, its imports,
its parents'), and it becomes a link when the API reference renders that object, plain code otherwise, without a
warning (``mkdocs build --strict`` stays clean). ``~a.b.c`` shows ``c``, as in Sphinx; names outside lnf
(``matplotlib.figure.Figure``) stay plain code. The source files are not changed.
"""
from __future__ import annotations

import html
import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:meth|func|class|attr|mod|data|obj|exc|const):`(?P<target>[^`]+)`")
PACKAGE = "lnf"


def _objects(obj: griffe.Object):
    yield obj
    for member in obj.members.values():
        if not member.is_alias:
            yield from _objects(member)


def _path(scope: griffe.Object, target: str) -> str | None:
    """The full path of `target` as the docstring of `scope` names it, or None outside the package."""
    first, _, rest = target.lstrip(".").partition(".")
    if first == PACKAGE:
        path = target
    else:
        try:
            path = scope.resolve(first) + (f".{rest}" if rest else "")
        except griffe.NameResolutionError:
            return None
    if path.split(".", 1)[0] != PACKAGE:
        return None
    try:  # the documented object's own path, when an import re-exports it (lnf.scenes.Scene -> lnf.scenes.base)
        return scope.modules_collection[path].canonical_path
    except Exception:  # noqa: BLE001 - an alias that does not resolve, a member griffe does not see: keep the path
        return path


def rewrite(text: str, scope: griffe.Object) -> str:
    def replace(match: re.Match) -> str:
        target = match.group("target").strip()
        short = target.startswith("~")
        target = target.lstrip("~")
        title = target.rsplit(".", 1)[-1] if short else target.lstrip(".")
        code = f"<code>{html.escape(title)}</code>"
        path = _path(scope, target)
        if path is None:
            return f"`{title}`"
        return f'<autoref identifier="{html.escape(path)}" optional>{code}</autoref>'

    return ROLE.sub(replace, text)


class SphinxRoles(griffe.Extension):
    """Rewrite the Sphinx roles of lnf's docstrings into optional cross-references (see the module docstring)."""

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        if pkg.name != PACKAGE:
            return
        for obj in _objects(pkg):
            if obj.docstring is not None and ROLE.search(obj.docstring.value):
                obj.docstring.value = rewrite(obj.docstring.value, obj)
