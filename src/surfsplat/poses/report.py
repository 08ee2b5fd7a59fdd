"""What `reconstruct` writes about cameras it estimated: the camera file of the photos, the pose
summary, and an HTML report that shows each photo beside its estimated camera.

    written = write_pose_outputs(out, camera_set, summary, image_paths, renders=[...])
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..data.cameras import CameraSet
from .estimate import PoseSummary

THUMBNAIL_WIDTH = 320  # pixels of the photo copies shown in the report


def write_pose_outputs(
    out_dir: str | Path,
    camera_set: CameraSet,
    summary: PoseSummary,
    image_paths: list[Path],  # every input photo, in input order (unregistered ones included)
    renders: list[Path] | None = None,  # colour renders of the registered views, beside the report
) -> dict[str, Path]:
    """Write estimated_cameras.json, poses.json, poses/ (thumbnails, top view) and report.html."""
    from ..data.cameras import save_cameras
    from ..data.images import read_image
    from ..export.figures import write_text
    from ..export.images import write_png
    from ..export.report import HtmlReport

    out = Path(out_dir)
    c = camera_set
    written = {
        "estimated cameras": save_cameras(
            out / "estimated_cameras.json",
            c.cameras,
            c.width,
            c.height,
            c.names,
            c.near,
            c.far,
            lenses=c.lenses,
        ),
        "pose summary": write_text(out / "poses.json", json.dumps(summary.to_dict(), indent=1) + "\n"),
    }
    report = HtmlReport("SurfSplat reconstruction from photos without poses")
    report.heading("Cameras estimated from the photos")
    report.preformatted("\n".join(summary.lines()))
    index = {name: k for k, name in enumerate(c.names)}
    first_R = c.cameras.c2w[0, :3, :3].to(torch.float64)
    figures, rows = [], []
    for k, path in enumerate(image_paths):
        name = summary.images[k]
        rgb, _ = read_image(path, background=(1.0, 1.0, 1.0))
        height = max(1, round(rgb.shape[1] * THUMBNAIL_WIDTH / rgb.shape[2]))
        thumb = F.interpolate(rgb[None], size=(height, THUMBNAIL_WIDTH), mode="area")[0]
        rel = f"poses/photo{k:02d}.png"
        write_png(out / rel, thumb)
        if name in index:
            i = index[name]
            centre = c.cameras.c2w[i, :3, 3].tolist()
            turn = _angle_deg(first_R.T @ c.cameras.c2w[i, :3, :3].to(torch.float64))
            f = float(c.cameras.K[i, 0, 0])
            caption = f"{name}: centre ({centre[0]:.2f}, {centre[1]:.2f}, {centre[2]:.2f}), turned {turn:.1f} deg, f {f:.0f} px"
            rows.append([name, "yes", *(f"{v:.3f}" for v in centre), f"{turn:.2f}", f"{f:.1f}"])
        else:
            caption = f"{name}: not registered (no camera)"
            rows.append([name, "no", "", "", "", "", ""])
        figures.append((rel, caption))
    report.figure_row(figures, width=THUMBNAIL_WIDTH)
    report.table(
        "Estimated cameras (world = the first camera, OpenCV axes: x right, y down, z forward)",
        ["photo", "registered", "centre x", "centre y", "centre z", "rotation from first (deg)", "focal (px)"],
        rows,
    )
    written["camera layout"] = write_text(out / "poses/cameras.svg", top_view_svg(c))
    report.figure("poses/cameras.svg", "Top view of the cameras (x right, z forward of the first camera)")
    if renders:
        shown = [(str(Path(p).relative_to(out)), f"render from the camera of {n}") for p, n in zip(renders, c.names)]
        report.heading("Reconstruction seen from the estimated cameras")
        report.figure_row(shown, width=THUMBNAIL_WIDTH)
    report.links(
        "Files:",
        [
            ("estimated_cameras.json", "cameras of the photos (K in their pixels), usable as --cameras"),
            ("poses.json", "the pose summary"),
        ],
    )
    written["report"] = report.write(out / "report.html")
    return written


def _angle_deg(R: torch.Tensor) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(torch.trace(R)) - 1) / 2))))


def top_view_svg(camera_set: CameraSet, size: int = 480) -> str:
    """An SVG of the cameras seen from above: the x-z plane of the first camera, each camera a
    dot and its horizontal field of view as a wedge, labelled with its photo's name where the label
    has room (`_place_labels`); every dot names its photo on hover."""
    # drawn on the host, wherever the cameras are
    c2w = camera_set.cameras.c2w.detach().to("cpu", torch.float64).numpy()
    K = camera_set.cameras.K.detach().to("cpu", torch.float64).numpy()
    widths = _view_widths(camera_set)
    centres = c2w[:, [0, 2], 3]
    span = max(float(np.ptp(centres, axis=0).max()), 1e-9)
    wedge = 0.5 * span  # wedge length: half the extent of the camera layout
    points = [centres]
    shapes = []
    for i in range(len(c2w)):
        half = math.atan(widths[i] / (2 * K[i, 0, 0]))
        axis = c2w[i, [0, 2], 2]
        axis = axis / max(np.linalg.norm(axis), 1e-12)
        left = _rotate(axis, -half) * wedge / math.cos(half) + centres[i]
        right = _rotate(axis, half) * wedge / math.cos(half) + centres[i]
        shapes.append((centres[i], left, right))
        points.append(np.stack([left, right]))
    every = np.concatenate(points)
    lo, hi = every.min(0), every.max(0)
    margin = 40
    scale = (size - 2 * margin) / max(float((hi - lo).max()), 1e-9)
    height = round(2 * margin + float(hi[1] - lo[1]) * scale)  # the picture is as deep as the layout

    def px(p: np.ndarray) -> str:
        # x to the right, z (forward) up the page
        return f"{margin + (p[0] - lo[0]) * scale:.1f},{height - margin - (p[1] - lo[1]) * scale:.1f}"

    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{size}" height="{height}" font-family="sans-serif">']
    parts.append(f'<rect width="{size}" height="{height}" fill="white" stroke="#ccc"/>')
    dots = []
    for (centre, left, right), name in zip(shapes, camera_set.names):
        parts.append(
            f'<polygon points="{px(centre)} {px(left)} {px(right)}" fill="#0072B2" fill-opacity="0.15" stroke="#0072B2"/>'
        )
        x, y = (float(v) for v in px(centre).split(","))
        dots.append((x, y))
        parts.append(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="3" fill="#D55E00"><title>{_escape(name)}</title></circle>')
    labels = _place_labels(dots, list(camera_set.names), size, height)
    for name, spot in zip(camera_set.names, labels):
        if spot is not None:
            parts.append(f'<text x="{spot[0]:.1f}" y="{spot[1]:.1f}" font-size="11">{_escape(name)}</text>')
    hidden = sum(spot is None for spot in labels)
    if hidden:
        parts.append(
            f'<text x="6" y="{height - 6}" font-size="10" fill="#666">{hidden} of {len(labels)} names hidden where '
            "they would overlap; hover a dot for its photo</text>"
        )
    parts.append("</svg>\n")
    return "\n".join(parts)


def _view_widths(camera_set: CameraSet) -> list[int]:
    """The width in pixels of each view's K: its pinhole's where the views have lenses (photos of several
    sizes each have their own), else the camera set's."""
    if camera_set.lenses is None:
        return [camera_set.width] * len(camera_set.names)
    from ..data.cameras import pinhole_of

    pinholes: dict = {}
    for lens in camera_set.lenses:
        if lens not in pinholes:
            pinholes[lens] = pinhole_of(lens).width
    return [pinholes[lens] for lens in camera_set.lenses]


_CHAR_W, _LINE_H = 6.2, 12.0  # rough extent of an 11-pixel sans-serif character


def _place_labels(
    dots: list[tuple[float, float]], names: list[str], width: float, height: float
) -> list[tuple[float, float] | None]:
    """Text anchors (x, baseline y) for each dot's name, or None where no spot beside the dot keeps
    the label inside the picture and clear of the labels placed before it and of the other dots.
    Greedy, in the cameras' order: the first camera of a tight cluster gets its name."""
    boxes: list[tuple[float, float, float, float]] = []
    out: list[tuple[float, float] | None] = []
    for i, ((x, y), name) in enumerate(zip(dots, names)):
        w = _CHAR_W * len(name)
        spot = None
        for dx, dy in ((5, 14), (5, -5), (-5 - w, 14), (-5 - w, -5)):
            box = (x + dx, y + dy - _LINE_H + 2, x + dx + w, y + dy + 2)
            inside = box[0] >= 0 and box[1] >= 0 and box[2] <= width and box[3] <= height
            clear = not any(_overlap(box, b) for b in boxes) and not any(
                _overlap(box, (ox - 3, oy - 3, ox + 3, oy + 3)) for j, (ox, oy) in enumerate(dots) if j != i
            )
            if inside and clear:
                spot = (box[0], y + dy)
                boxes.append(box)
                break
        out.append(spot)
    return out


def _overlap(a: tuple[float, float, float, float], b: tuple[float, float, float, float]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _rotate(v: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def _escape(text: str) -> str:
    return html.escape(text)
