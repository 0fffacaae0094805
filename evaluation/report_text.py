"""Text and paths as the report writes them into report.html and report.md.

Everything the report shows comes from files of the run and the scene (view names, setting
values, notes), so it is shown, never interpreted, in both files:

- `plain`: control and format characters (a newline in a setting value, U+202E that reverses
  the text after it, zero-width characters) become visible escapes (`\\n`, `\\u202e`);
- `html_text`: that, HTML-escaped;
- `md_text`: that, with every character Markdown could read as markup backslash-escaped (links,
  images: a remote image is a web beacon, emphasis, headings, tables, inline HTML, entities);
- `url`: a relative path percent-encoded, for a link or an image in either file (names such as
  `Küche 1 [Süd]` are allowed);
- `fmt`: a value read from an artifact, formatted whatever it holds: a run whose training diverged
  has metrics that are null or NaN, and the report shows them as missing rather than failing.
"""

from __future__ import annotations

import html
import math
import re
import unicodedata
from urllib.parse import quote

#: Characters Markdown may read as markup wherever they stand, backslash-escaped (CommonMark lets any
#: ASCII punctuation be): no link or image without its brackets, no emphasis, code, heading, table
#: cell or strikethrough. `<`, `>` and `&` become HTML entities (no autolink, inline HTML or entity).
_MD_ANYWHERE = set("\\`*[]|#~")
#: `_` opens or closes emphasis only where it is not between two letters or digits (`test_00` is plain).
_MD_UNDERSCORE = re.compile(r"(?<![^\W_])_|_(?![^\W_])")
#: At the start of a paragraph only: list items and setext underlines ("- x", "+ x", "="), ordered lists ("1. x").
_MD_BULLET = re.compile(r"^([+\-=])")
_MD_ORDERED = re.compile(r"^(\d+)([.)])")


def plain(text) -> str:
    """`text` as a string with control (Cc) and format (Cf) characters shown as escapes."""
    return "".join(repr(c)[1:-1] if unicodedata.category(c) in ("Cc", "Cf") else c for c in str(text))


def html_text(text) -> str:
    return html.escape(plain(text))


def md_text(text, paragraph_start: bool = False) -> str:
    """`text` for report.md: shown as it is by any Markdown renderer (and its inline HTML shown,
    not interpreted, as report.html shows it). `paragraph_start`: the text begins a line, where
    `- `, `+ `, `1. ` would start a list."""
    escaped = "".join("\\" + c if c in _MD_ANYWHERE else c for c in plain(text))
    escaped = html.escape(_MD_UNDERSCORE.sub(r"\\_", escaped), quote=False)
    if paragraph_start:
        escaped = _MD_ORDERED.sub(r"\1\\\2", _MD_BULLET.sub(r"\\\1", escaped))
    return escaped


def url(rel_path: str) -> str:
    """A relative path (POSIX separators) percent-encoded for a link or an image source."""
    return quote(plain(rel_path), safe="/")


#: How the report shows a value that is not there (null, NaN, a field the artifact lacks).
MISSING = "—"


def fmt(value, spec: str = ".4g") -> str:
    """`value` formatted with `spec` when it is a number; MISSING for None and NaN; yes/no for a
    boolean; other values as text."""
    if value is None:
        return MISSING
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int | float):
        if math.isnan(value):
            return MISSING
        return format(value, spec) if math.isfinite(value) else str(value)
    return str(value)


def missing_fields(record: dict, keys) -> list[str]:
    """The `keys` a record (an artifact's data, a view's metrics) holds no number for."""
    return [k for k in keys if fmt(record.get(k)) == MISSING]
