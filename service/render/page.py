"""The frame of the HTML pages kincal writes and serves: one inline style sheet, no scripts, no
external resources (the reports and the checks page render offline and under a
Content-Security-Policy of ``default-src 'none'``). Standard library only: a request process
loads matplotlib with the first page that draws a figure, not when it starts."""

from __future__ import annotations

import html

STYLE = """
body { font: 14px/1.45 system-ui, sans-serif; margin: 2rem auto; max-width: 72rem; color: #222; }
h1 { font-size: 1.5rem; } h2 { font-size: 1.15rem; margin-top: 2rem; }
table { border-collapse: collapse; margin: .5rem 0; }
th, td { border: 1px solid #ccc; padding: .25rem .6rem; text-align: right; }
th:first-child, td:first-child { text-align: left; }
table.text td { text-align: left; }
.warn { background: #fff4e0; border-left: 4px solid #e69500; padding: .4rem .8rem; }
.ok { background: #eaf6ea; border-left: 4px solid #3a3; padding: .4rem .8rem; }
img { max-width: 100%; } pre { background: #f6f6f6; padding: .6rem; overflow-x: auto; }
code { background: #f2f2f2; padding: 0 .2rem; }
"""


def html_page(title: str, sections: list[str], style: str = "") -> str:
    """A self-contained HTML page (inline style, no scripts) from HTML ``sections``; ``style``
    is added to the common one."""
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{html.escape(title)}</title><style>{STYLE}{style}</style></head>"
        f"<body>{''.join(sections)}</body></html>\n"
    )
