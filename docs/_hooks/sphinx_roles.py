"""MkDocs hook: the docstrings' Sphinx roles (:func:`x`, :class:`~a.b.C`) shown as code, as a reader expects,
instead of the raw role (``~`` keeps the last name only, as in Sphinx)."""

import re

_ROLE = re.compile(r":(?:func|meth|class|mod|data|attr|obj|exc):(<code>)(~?)([^<]*)(</code>)")


def _show(match: re.Match) -> str:
    name = match.group(3).rsplit(".", 1)[-1] if match.group(2) else match.group(3)
    return f"{match.group(1)}{name}{match.group(4)}"


def on_page_content(html, **kwargs):
    return _ROLE.sub(_show, html)
