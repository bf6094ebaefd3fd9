"""Escaping of untrusted ids (QR payloads, manifest cells) wherever they are written.

- CSV: a cell starting with = + - @ tab or CR is a formula to a spreadsheet (OWASP "CSV
  injection"); it gets a leading apostrophe, which spreadsheets show as text.
- Markdown: characters with a Markdown or HTML meaning are backslash-escaped / entity-encoded so
  an id cannot open a link, a table cell, an image or raw HTML.
- HTML (plotly hover text is rendered as HTML): `html.escape`.
"""

from __future__ import annotations

import html

CSV_FORMULA_PREFIXES = ("=", "+", "-", "@", "\t", "\r")
_MD_SPECIAL = set("\\`*_{}[]()#+-.!|>~")


def csv_cell(text: str) -> str:
    """`text` safe for a CSV cell opened by a spreadsheet: a leading ' before formula starters."""
    text = str(text)
    return "'" + text if text.startswith(CSV_FORMULA_PREFIXES) else text


def markdown(text: str) -> str:
    """`text` as literal Markdown text (also inside a table cell): specials backslash-escaped,
    < > & as HTML entities, line breaks as spaces."""
    out = []
    for ch in str(text).replace("\r", " ").replace("\n", " "):
        if ch == "&":
            out.append("&amp;")
        elif ch == "<":
            out.append("&lt;")
        elif ch == ">":
            out.append("&gt;")
        elif ch in _MD_SPECIAL:
            out.append("\\" + ch)
        else:
            out.append(ch)
    return "".join(out)


def html_text(text: str) -> str:
    """`text` for HTML (plotly hover text): & < > " ' as entities."""
    return html.escape(str(text), quote=True)
