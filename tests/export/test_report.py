"""Image grids, SVG charts and the HTML report: exact placement, parsable output, refused broken links."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from html.parser import HTMLParser

import pytest
import torch

from surfsplat.export.figures import image_grid, line_chart, smooth, write_text
from surfsplat.export.images import write_png
from surfsplat.export.report import HtmlReport
from surfsplat.utils.checks import SurfSplatInputError

SVG = "{http://www.w3.org/2000/svg}"


def test_image_grid_places_cells_exactly_and_keeps_x1_pixels():
    torch.manual_seed(0)
    big = torch.rand(3, 8, 8)
    small = torch.rand(3, 2, 2)
    grid = image_grid([[big, small], [None, big[:1]]], size=(8, 8), padding=1, background=0.25)
    assert grid.shape == (3, 1 + 2 * 9, 1 + 2 * 9)
    torch.testing.assert_close(grid[:, 1:9, 1:9], big)
    # Nearest-neighbour resampling: each x1 pixel becomes a 4x4 block, never a blend.
    cell = grid[:, 1:9, 10:18]
    torch.testing.assert_close(cell, small.repeat_interleave(4, 1).repeat_interleave(4, 2))
    assert torch.all(grid[:, 10:18, 1:9] == 0.25)  # the empty cell
    torch.testing.assert_close(grid[:, 10:18, 10:18], big[:1].expand(3, 8, 8))


def test_image_grid_errors():
    with pytest.raises(SurfSplatInputError, match="at least one image"):
        image_grid([[None]])
    with pytest.raises(SurfSplatInputError, match="image 0 must be a"):
        image_grid([[torch.rand(4, 2, 2)]])


def test_line_chart_is_valid_svg_with_points_in_order():
    loss = [(s, 1.0 / (s + 1)) for s in range(50)]
    svg = line_chart({"loss": loss, "smooth": smooth(loss, 5)}, title="Loss <MSE>", log_y=True)
    root = ET.fromstring(svg)
    lines = root.findall(f"{SVG}polyline")
    assert len(lines) == 2
    points = [tuple(map(float, p.split(","))) for p in lines[0].get("points").split()]
    assert len(points) == 50
    xs, ys = zip(*points)
    assert all(b > a for a, b in zip(xs, xs[1:]))  # x increases left to right
    assert all(b > a for a, b in zip(ys, ys[1:]))  # a falling loss goes down the picture (SVG y grows downwards)
    # Log axis: equal ratios of the value are equal vertical steps.
    y1, y3, y9 = ys[0], ys[2], ys[8]  # values 1, 1/3, 1/9
    assert math.isclose(y3 - y1, y9 - y3, rel_tol=1e-2)
    assert "Loss &lt;MSE&gt;" in svg


def test_smooth_is_a_trailing_mean():
    assert smooth([(0, 1.0), (1, 3.0), (2, 5.0)], 2) == [(0, 1.0), (1, 2.0), (2, 4.0)]
    with pytest.raises(SurfSplatInputError):
        smooth([(0, 1.0)], 0)


class _Links(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.sources: list[str] = []

    def handle_starttag(self, tag, attrs):
        if tag in ("img", "video"):
            self.sources.append(dict(attrs)["src"])


def test_report_links_its_figures_and_escapes_text(tmp_path):
    write_png(tmp_path / "figs" / "a.png", torch.rand(3, 4, 4))
    write_text(tmp_path / "curve.svg", line_chart({"x": [(0, 1), (1, 2)]}))
    report = HtmlReport("Demo <1>")
    report.paragraph("a < b & c")
    report.table("T", ["name", "value"], [["x", 1.23456], ["y", None]])
    report.figure_row([("figs/a.png", "A")], width=100, pixelated=True)
    report.figure("curve.svg", "curve")
    path = report.write(tmp_path / "report.html")
    text = path.read_text()
    assert "Demo &lt;1&gt;" in text and "a &lt; b &amp; c" in text
    assert "<td>1.235</td>" in text and "<td>n/a</td>" in text
    parser = _Links()
    parser.feed(text)
    assert parser.sources == ["figs/a.png", "curve.svg"]


def test_report_refuses_missing_figures_and_ragged_tables(tmp_path):
    report = HtmlReport("x")
    report.figure("missing.png", "gone")
    with pytest.raises(SurfSplatInputError, match="missing files"):
        report.write(tmp_path / "report.html")
    assert not (tmp_path / "report.html").exists()
    with pytest.raises(SurfSplatInputError, match="row 0 has 1 cells"):
        HtmlReport("x").table("T", ["a", "b"], [["only one"]])
