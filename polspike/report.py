"""A self-contained HTML report: sections of text, tables and embedded PNG figures."""

from __future__ import annotations

import base64
import html
import os
from pathlib import Path

from polinfra.atomic import write_text

__all__ = ["Report"]


class Report:
    """Accumulate sections, then write one HTML file with every image embedded (base64)."""

    def __init__(self, title: str):
        self.title = title
        self.sections: list[tuple[str, str, str]] = []  # (id, heading, html body)

    def section(self, sid: str, heading: str) -> "_Section":
        body: list[str] = []
        self.sections.append((sid, heading, ""))
        return _Section(self, len(self.sections) - 1, body)

    def write(self, path: str | os.PathLike) -> Path:
        toc = "".join(f'<li><a href="#{sid}">{html.escape(h)}</a></li>' for sid, h, _ in self.sections)
        secs = "".join(f'<section id="{sid}"><h2>{html.escape(h)}</h2>{body}</section>' for sid, h, body in self.sections)
        doc = f"""<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>{html.escape(self.title)}</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:auto;padding:1em;color:#222}}img{{max-width:100%;border:1px solid #ddd}}
table{{border-collapse:collapse;margin:0.5em 0}}td,th{{border:1px solid #ccc;padding:3px 8px;text-align:right}}th{{background:#f3f3f3}}
pre{{background:#f6f6f6;padding:0.6em;overflow-x:auto}}.ok{{color:#070;font-weight:bold}}.bad{{color:#b00;font-weight:bold}}</style></head>
<body><h1>{html.escape(self.title)}</h1><ol>{toc}</ol>{secs}</body></html>"""
        return write_text(path, doc)


class _Section:
    def __init__(self, report: Report, idx: int, body: list[str]):
        self.report, self.idx, self.body = report, idx, body

    def _flush(self) -> "_Section":
        sid, h, _ = self.report.sections[self.idx]
        self.report.sections[self.idx] = (sid, h, "".join(self.body))
        return self

    def text(self, s: str, cls: str | None = None) -> "_Section":
        c = f' class="{cls}"' if cls else ""
        self.body.append(f"<p{c}>{html.escape(s)}</p>")
        return self._flush()

    def code(self, s: str) -> "_Section":
        self.body.append(f"<pre>{html.escape(s)}</pre>")
        return self._flush()

    def image(self, png: str | os.PathLike, alt: str) -> "_Section":
        data = base64.b64encode(Path(png).read_bytes()).decode()
        self.body.append(f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{data}"><figcaption>{html.escape(alt)}</figcaption></figure>')
        return self._flush()

    def table(self, header: list[str], rows: list[list[object]]) -> "_Section":
        th = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
        trs = "".join("<tr>" + "".join(f"<td>{html.escape(_fmt(v))}</td>" for v in r) + "</tr>" for r in rows)
        self.body.append(f"<table><tr>{th}</tr>{trs}</table>")
        return self._flush()


def _fmt(v: object) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)
