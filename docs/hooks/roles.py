"""MkDocs hook: the docstrings' Sphinx roles (``:class:`~satloc.geometry.Pose2` ``) shown as code.

The docstrings are written for reading in source and in ``help()``; mkdocstrings renders them as Markdown,
where a role arrives as ``:class:<code>~satloc.geometry.Pose2</code>``. This drops the role's name and, for a
``~`` target, keeps the last component as Sphinx does.
"""
import re

_ROLE = re.compile(r":(?:class|func|meth|mod|attr|data|exc|obj|const):<code>(~?)([^<]+)</code>")


def _sub(m: re.Match) -> str:
    target = m.group(2)
    return f"<code>{target.rsplit('.', 1)[-1] if m.group(1) else target}</code>"


def on_page_content(html, **kwargs):
    return _ROLE.sub(_sub, html)
