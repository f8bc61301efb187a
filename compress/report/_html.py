"""Text of the page: escaping, numbers as text, tables, the page template and its CSS.

The style sheet is inline, with a print style; the provenance table lists ``info``.
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

_CSS = """
:root { --ink: #1b1b1b; --muted: #555; --rule: #d0d0d0; }
body { margin: 0; color: var(--ink); background: #fff;
  font: 15px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; }
main { max-width: 1120px; margin: 0 auto; padding: 1.2rem 1.4rem 3rem; }
h1 { font-size: 1.6rem; margin: 0.2rem 0 0.3rem; }
h2 { font-size: 1.25rem; margin: 1.8rem 0 0.5rem; border-bottom: 1px solid var(--rule);
  padding-bottom: 0.2rem; }
h3 { font-size: 1.05rem; margin: 1.1rem 0 0.4rem; }
p.lead { color: var(--muted); margin-top: 0; }
table { border-collapse: collapse; margin: 0.4rem 0 0.8rem; font-size: 0.9rem; }
th, td { text-align: left; padding: 0.18rem 0.7rem 0.18rem 0; vertical-align: top;
  border-bottom: 1px solid #eee; }
th { font-weight: 600; border-bottom: 1px solid var(--rule); }
td:first-child { white-space: nowrap; }
td.num { font-variant-numeric: tabular-nums; }
figure { margin: 0.6rem 0 1rem; }
figcaption { color: var(--muted); font-size: 0.88rem; max-width: 62rem; }
img { max-width: 100%; height: auto; display: block; }
details summary { cursor: pointer; color: var(--muted); }
code { font-size: 0.9em; }
@media print {
  body { font-size: 10pt; }
  main { max-width: none; padding: 0; }
  section, figure, table { break-inside: avoid; page-break-inside: avoid; }
  h2 { break-after: avoid; page-break-after: avoid; }
  details > *:not(summary) { display: block; }
  details summary { display: none; }
  img { max-width: 100% !important; }
}
"""

#: Where :func:`_notes` goes: the warnings are known only once the page is made.
_NOTES = "<!--notes-->"


def _document(title: str, lead: str, body: str) -> str:
    """Return the whole page: ``title`` is plain text, ``lead`` and ``body`` are HTML."""
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
            f"<title>{_e(title)}: scatmodes report</title><style>{_CSS}</style>"
            f"</head><body><main><h1>{_e(title)}</h1><p class=\"lead\">"
            f"{lead}</p>\n{body}\n{_NOTES}\n</main></body></html>\n")


def _notes(page: str, messages: Sequence[str]) -> str:
    """Put the section listing ``messages`` (warnings, each once) into ``page``."""
    if not messages:
        return page
    items = "".join(f"<li>{_e(n)}</li>" for n in dict.fromkeys(messages))
    return page.replace(_NOTES, f"<section><h2>Notes</h2><p>Warnings raised "
                        f"while this page was made:</p><ul>{items}</ul></section>")


def _e(text: str) -> str:
    return html.escape(str(text), quote=True)


def _p(text: str) -> str:
    return f"<p>{_e(text)}</p>" if text else ""


def _finite(x: Any) -> bool:
    return isinstance(x, int | float | np.floating | np.integer) and not isinstance(x, bool) \
        and math.isfinite(float(x))


def _num(x: Any) -> str:
    """Four significant digits; "n/a" for None and non-finite numbers."""
    return f"{float(x):.4g}" if _finite(x) else "n/a"


def _short(text: str, width: int = 160) -> str:
    text = " ".join(text.split())
    return text if len(text) <= width else text[:width - 3] + "..."


def _table(head: list[str], rows: Sequence[Sequence[str]], *, raw: bool = False) -> str:
    """Format an HTML table; cells are escaped unless ``raw`` (already escaped)."""
    cell = (lambda c: str(c)) if raw else _e
    out = ["<table><thead><tr>", *(f"<th>{_e(h)}</th>" for h in head), "</tr></thead><tbody>"]
    for r in rows:
        out.append("<tr>" + "".join(f"<td>{cell(c)}</td>" for c in r) + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def _provenance(info: Any) -> str:
    if not isinstance(info, Mapping) or not info:
        return "<p>None recorded.</p>"
    rows = []
    for k, v in info.items():
        if k == "candidates" and isinstance(v, list):
            text = f"{len(v)} rows (section 5)"
        elif k == "selected" and isinstance(v, Mapping):
            text = (f"{v.get('label')} at {v.get('dtype')}: {v.get('bytes')} bytes, "
                    f"l2 {_num(v.get('l2'))}")
        elif isinstance(v, float):
            text = _num(v)
        elif isinstance(v, int) and not isinstance(v, bool):
            text = f"{v:,}"
        elif isinstance(v, Mapping):
            text = ", ".join(f"{a}: {_num(b) if isinstance(b, float) else b}"
                             for a, b in v.items())
        elif isinstance(v, np.ndarray):
            text = np.array2string(v, precision=4, threshold=8)
        else:
            text = str(v)
        rows.append((str(k), _short(text, 300)))
    return _table(["info key", "value"], rows)
