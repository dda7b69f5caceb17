"""MkDocs hook: the docstrings' Sphinx cross-reference roles read as plain code on the site.

The code's docstrings use roles such as ``:func:`opt``` and ``:class:`~pkg.Cls```; Markdown renders the
role's name as text before the code. The hook drops the role name and Sphinx's leading ``~``.
"""

from __future__ import annotations

import re

_ROLE = re.compile(r":(?:func|class|mod|meth|attr|data|obj|exc|const|ref|doc):(?=<code)")
_TILDE = re.compile(r"<code>~")


def on_page_content(html: str, **kwargs) -> str:
    return _TILDE.sub("<code>", _ROLE.sub("", html))
