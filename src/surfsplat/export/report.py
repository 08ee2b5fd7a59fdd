"""A self-contained HTML report: text, tables and figures that sit beside it as PNG/SVG files.

    report = HtmlReport("SurfSplat demo")
    report.paragraph("Trained the tiny preset for 120 steps.")
    report.table("Metrics", ["Resolution", "PSNR"], [["64x64", "24.1"]])
    report.figure("renders/grid.png", "Ground truth and renders at x1, x2, x4")
    report.write("out/report.html")

Figures are referenced by relative paths, so the folder can be moved or zipped as a whole; the
report refuses figures that do not exist (a report with broken images is worse than an error).
"""

from __future__ import annotations

import html
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ..utils.checks import SurfSplatInputError
from .figures import write_text

_STYLE = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { font-size: 1.6em; } h2 { font-size: 1.25em; margin-top: 1.6em; border-bottom: 1px solid #ddd; }
table { border-collapse: collapse; margin: 0.6em 0; font-variant-numeric: tabular-nums; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: right; } th { background: #f3f3f3; }
td:first-child, th:first-child { text-align: left; }
figure { display: inline-block; margin: 0.4em 0.8em 0.8em 0; vertical-align: top; width: min-content; }
figcaption { font-size: 0.85em; color: #555; max-width: 520px; }
img.pixel { image-rendering: pixelated; }
pre { background: #f6f6f6; padding: 0.6em; overflow-x: auto; font-size: 0.85em; }
.note { color: #8a4b00; }
"""


@dataclass
class HtmlReport:
    """Blocks of a report in order; `write` renders them to one HTML file."""

    title: str
    blocks: list[str] = field(default_factory=list)
    figures: list[str] = field(default_factory=list)  # relative paths of every figure, for checks

    def heading(self, text: str) -> None:
        self.blocks.append(f"<h2>{html.escape(text)}</h2>")

    def paragraph(self, text: str, note: bool = False) -> None:
        cls = ' class="note"' if note else ""
        self.blocks.append(f"<p{cls}>{html.escape(text)}</p>")

    def preformatted(self, text: str) -> None:
        self.blocks.append(f"<pre>{html.escape(text)}</pre>")

    def table(
        self,
        caption: str,
        header: Sequence[str],
        rows: Sequence[Sequence[object]],
        header_rows: Sequence[Sequence[tuple[str, int]]] = (),
    ) -> None:
        """A table; `header_rows` are extra header lines above `header` as (text, column span) cells."""
        width = len(header)
        for r, row in enumerate(rows):
            if len(row) != width:
                raise SurfSplatInputError(f"table {caption!r}: row {r} has {len(row)} cells, the header {width}")
        parts = ["<table>", f"<caption>{html.escape(caption)}</caption>" if caption else ""]
        for extra in header_rows:
            parts.append(
                "<tr>" + "".join(f'<th colspan="{span}">{html.escape(text)}</th>' for text, span in extra) + "</tr>"
            )
        parts.append("<tr>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in header) + "</tr>")
        for row in rows:
            parts.append("<tr>" + "".join(f"<td>{html.escape(_cell(c))}</td>" for c in row) + "</tr>")
        parts.append("</table>")
        self.blocks.append("".join(parts))

    def figure(self, path: str, caption: str, width: int | None = None, pixelated: bool = False) -> None:
        """An image (PNG/SVG) at `path` relative to the report; `width` in CSS pixels."""
        attrs = f' width="{width}"' if width else ""
        cls = ' class="pixel"' if pixelated else ""
        src = html.escape(path, quote=True)
        self.blocks.append(
            f'<figure><a href="{src}"><img src="{src}" alt="{html.escape(caption, quote=True)}"{attrs}{cls}></a>'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>"
        )
        self.figures.append(path)

    def figure_row(self, items: Sequence[tuple[str, str]], width: int | None = None, pixelated: bool = False) -> None:
        """Several (path, caption) figures side by side, each shown `width` pixels wide."""
        self.blocks.append("<div>")
        for path, caption in items:
            self.figure(path, caption, width, pixelated)
        self.blocks.append("</div>")

    def video(self, path: str, caption: str, width: int | None = None) -> None:
        attrs = f' width="{width}"' if width else ""
        src = html.escape(path, quote=True)
        self.blocks.append(
            f'<figure><video src="{src}" controls loop muted autoplay playsinline{attrs}></video>'
            f'<figcaption>{html.escape(caption)} (<a href="{src}">{html.escape(path)}</a>)</figcaption></figure>'
        )
        self.figures.append(path)

    def links(self, caption: str, items: Sequence[tuple[str, str]]) -> None:
        """A list of (relative path, description) links to the other outputs."""
        rows = "".join(
            f'<li><a href="{html.escape(p, quote=True)}">{html.escape(p)}</a>: {html.escape(d)}</li>' for p, d in items
        )
        self.blocks.append(f"<p>{html.escape(caption)}</p><ul>{rows}</ul>")

    def render(self) -> str:
        body = "\n".join(self.blocks)
        return (
            '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f"<title>{html.escape(self.title)}</title><style>{_STYLE}</style></head>\n"
            f"<body><h1>{html.escape(self.title)}</h1>\n{body}\n</body></html>\n"
        )

    def write(self, path: str | os.PathLike) -> Path:
        """Write the HTML (atomically) after checking that every referenced file exists beside it."""
        path = Path(path)
        missing = [p for p in self.figures if not (path.parent / p).is_file()]
        if missing:
            raise SurfSplatInputError(f"{path}: the report refers to missing files {missing}")
        return write_text(path, self.render())


def _cell(value: object) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return f"{value:.3f}"
    return str(value)
