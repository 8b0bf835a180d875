"""A small document model rendered to both Markdown and HTML, and number formatting."""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["Doc", "fmt", "num", "pct"]


class Doc:
    def __init__(self) -> None:
        self.blocks: list[tuple[str, Any]] = []

    def h(self, level: int, text: str) -> None:
        self.blocks.append(("h", (level, text)))

    def p(self, text: str) -> None:
        self.blocks.append(("p", text))

    def ul(self, items: Sequence[str]) -> None:
        self.blocks.append(("ul", list(items)))

    def code(self, text: str) -> None:
        self.blocks.append(("code", text))

    def table(self, header: Sequence[str], rows: Sequence[Sequence[str]]) -> None:
        self.blocks.append(("table", (list(header), [list(r) for r in rows])))

    def img(self, path: str, alt: str) -> None:
        self.blocks.append(("img", (path, alt)))

    def markdown(self) -> str:
        out = []
        for kind, val in self.blocks:
            if kind == "h":
                out.append("#" * val[0] + " " + val[1])
            elif kind == "p":
                out.append(val)
            elif kind == "code":
                out.append("```\n" + val + "\n```")
            elif kind == "ul":
                out.append("\n".join(f"- {item}" for item in val))
            elif kind == "img":
                out.append(f"![{val[1]}]({val[0]})")
            elif kind == "table":
                header, rows = val
                lines = [
                    "| " + " | ".join(header) + " |",
                    "|" + "|".join("---" for _ in header) + "|",
                ]
                lines += ["| " + " | ".join(r) + " |" for r in rows]
                out.append("\n".join(lines))
        return "\n\n".join(out) + "\n"

    def html(self, title: str) -> str:
        body = []
        for kind, val in self.blocks:
            if kind == "h":
                body.append(f"<h{val[0]}>{html.escape(val[1])}</h{val[0]}>")
            elif kind == "p":
                body.append(f"<p>{_inline_html(val)}</p>")
            elif kind == "code":
                body.append(f"<pre><code>{html.escape(val)}</code></pre>")
            elif kind == "ul":
                items = "".join(f"<li>{_inline_html(item)}</li>" for item in val)
                body.append(f"<ul>{items}</ul>")
            elif kind == "img":
                src, alt = (html.escape(v, quote=True) for v in val)
                body.append(
                    f'<figure><img src="{src}" alt="{alt}" loading="eager">'
                    f"<figcaption>{html.escape(val[1])}</figcaption></figure>"
                )
            elif kind == "table":
                header, rows = val
                th = "".join(f"<th>{html.escape(c)}</th>" for c in header)
                trs = "".join(
                    "<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>"
                    for r in rows
                )
                body.append(
                    f'<div class="scroll"><table><thead><tr>{th}</tr></thead>'
                    f"<tbody>{trs}</tbody></table></div>"
                )
        return _HTML_TEMPLATE.format(title=html.escape(title), body="\n".join(body))


def _inline_html(text: str) -> str:
    # Markdown's `code` spans and **bold** only; everything else escaped.
    parts = html.escape(text).split("`")
    out = []
    for i, part in enumerate(parts):
        if i % 2:
            out.append(f"<code>{part}</code>")
        else:
            bold = part.split("**")
            out.append("".join(f"<b>{b}</b>" if j % 2 else b for j, b in enumerate(bold)))
    return "".join(out)


_HTML_TEMPLATE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title>
<style>
body {{ font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 24px auto;
       max-width: 1240px; padding: 0 16px; color: #1b1b1b; background: #fff; line-height: 1.45; }}
h1 {{ font-size: 1.7em; border-bottom: 2px solid #345; padding-bottom: 4px; }}
h2 {{ font-size: 1.3em; margin-top: 1.6em; color: #234; }}
h3 {{ font-size: 1.1em; color: #234; }}
table {{ border-collapse: collapse; font-size: 0.82em; margin: 8px 0 16px; }}
th, td {{ border: 1px solid #c8ccd2; padding: 3px 7px; text-align: right; white-space: nowrap; }}
th {{ background: #e8edf3; position: sticky; top: 0; }}
td:first-child, th:first-child {{ text-align: left; }}
tr:nth-child(even) td {{ background: #f6f8fa; }}
.scroll {{ overflow-x: auto; }}
figure {{ margin: 12px 0 20px; }}
figure img {{ max-width: 100%; height: auto; border: 1px solid #dde; }}
figcaption {{ font-size: 0.85em; color: #555; }}
code, pre {{ background: #f3f4f6; border-radius: 3px; }}
pre {{ padding: 8px; overflow-x: auto; }}
</style>
</head>
<body>
{body}
</body>
</html>
"""


def fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "–"
    if isinstance(v, int | np.integer) and not isinstance(v, bool):
        return str(int(v))
    v = float(v)
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    if not math.isfinite(v):
        return "–"
    if v != 0 and (abs(v) < 10**-(digits) or abs(v) >= 1e5):
        return f"{v:.{digits - 1}e}"
    return f"{v:.{digits}f}" if abs(v) < 10 else f"{v:.{max(0, digits - 2)}f}"


def pct(v: Any) -> str:
    if v is None or not math.isfinite(float(v)):
        return "–"
    return f"{100 * float(v):.1f} %"


def num(v: Any) -> float:
    return math.nan if v is None else float(v)
