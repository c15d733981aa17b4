"""MkDocs hook: every page gets the glossary's abbreviations (docs/glossary.md's table) as Markdown
abbreviations, so that each occurrence shows its expansion on hover (the ``abbr`` extension)."""
import re
from pathlib import Path

_ROW = re.compile(r"^\| ([A-Za-z][A-Za-z0-9-]*) \| (.+) \|$")
_CACHE: dict = {}


def _definitions(docs_dir: str) -> str:
    if docs_dir not in _CACHE:
        lines = []
        for line in (Path(docs_dir) / "glossary.md").read_text().splitlines():
            m = _ROW.match(line)
            if m and m.group(1) != "abbreviation":
                short = m.group(2).split(":")[0].strip()
                lines.append(f"*[{m.group(1)}]: {short}")
        _CACHE[docs_dir] = "\n\n" + "\n".join(lines) + "\n"
    return _CACHE[docs_dir]


def on_page_markdown(markdown, page, config, **kwargs):
    return markdown + _definitions(config["docs_dir"])
