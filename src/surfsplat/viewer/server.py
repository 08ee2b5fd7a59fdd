"""The viewer's HTTP server: the page, the scene description and the packed splats, on localhost.

Routes:
    /            the page (surfsplat.viewer.page.PAGE)
    /meta.json   {"count", "center", "radius", "camera": {"position", "target", "up", "fov_deg"}, "title",
                  "alpha_threshold"}
    /splats.bin  count x 8 little-endian float32: x, y, z, r, g, b, opacity, radius (world units)
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import torch

from ..checks import SurfSplatInputError
from ..gaussians import Gaussians
from ..geometry.sh import SH_C0
from .page import PAGE


@dataclass
class InitialView:
    """Where the page's camera starts (world frame)."""

    position: list[float]
    target: list[float]
    up: list[float]
    fov_deg: float = 50.0


def splat_buffer(gaussians: Gaussians, max_splats: int = 300_000, seed: int = 0) -> tuple[bytes, dict]:
    """Pack unbatched Gaussians for the page: (bytes, meta without camera).

    Colour is the view-independent SH DC term (0.5 + C0 * dc, clamped to [0, 1]); the radius is
    the larger tangent scale. More than `max_splats` surfels are subsampled (seeded, so the same
    file always shows the same subset) to keep the page interactive.
    """
    g = gaussians.detach().to("cpu")
    if g.means.ndim != 2:
        raise SurfSplatInputError(f"gaussians: expected unbatched Gaussians ([N, 3] means), got {tuple(g.means.shape)}")
    n = len(g)
    if n == 0:
        raise SurfSplatInputError("gaussians: the file holds no surfels")
    if max_splats < 1:
        raise SurfSplatInputError(f"max_splats: expected at least 1, got {max_splats}")
    keep = torch.arange(n)
    if n > max_splats:
        keep = torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:max_splats].sort().values
    means = g.means[keep].double()
    rgb = (0.5 + SH_C0 * g.sh[keep, :, 0].double()).clamp(0, 1)
    radius = g.scales[keep].double().amax(-1)
    data = torch.cat([means, rgb, g.opacities[keep].double()[:, None], radius[:, None]], dim=1)
    packed = data.numpy().astype("<f4").tobytes()
    lo, hi = torch.quantile(means, torch.tensor([0.02, 0.98], dtype=torch.float64), dim=0)
    center = ((lo + hi) / 2).tolist()
    extent = float((hi - lo).norm() / 2)
    return packed, {"count": int(keep.numel()), "total": n, "center": center, "radius": max(extent, 1e-6)}


def initial_view(meta: dict, cameras=None) -> InitialView:
    """The first camera of a reconstruction when given (looking along its axis), else a view from -z."""
    center = meta["center"]
    if cameras is not None and len(cameras) > 0:
        c2w = cameras.c2w[0].to(torch.float64)
        eye = c2w[:3, 3]
        forward = c2w[:3, 2]
        depth = float(torch.dot(torch.tensor(center, dtype=torch.float64) - eye, forward))
        target = eye + forward * max(depth, 1e-3)
        fy = float(cameras.K[0, 1, 1])
        height = float(cameras.K[0, 1, 2]) * 2
        fov = float(2 * np.degrees(np.arctan(height / (2 * fy))))
        return InitialView(eye.tolist(), target.tolist(), (-c2w[:3, 1]).tolist(), fov)
    r = meta["radius"]
    position = [center[0], center[1], center[2] - 2.5 * r]
    return InitialView(position, list(center), [0.0, -1.0, 0.0])


class ViewerServer:
    """Serves one scene on host:port (port 0 picks a free one) from a background thread."""

    def __init__(
        self,
        gaussians: Gaussians,
        host: str = "127.0.0.1",
        port: int = 8080,
        cameras=None,
        title: str = "surfsplat viewer",
        max_splats: int = 300_000,
        alpha_threshold: float | None = 0.001,
    ) -> None:
        if not 0 <= port <= 65535:
            raise SurfSplatInputError(f"port: expected 0..65535, got {port}")
        if alpha_threshold is not None and not 0 < alpha_threshold <= 1:
            raise SurfSplatInputError(f"alpha_threshold: expected a value in (0, 1] or None, got {alpha_threshold}")
        payload, meta = splat_buffer(gaussians, max_splats)
        meta["camera"] = initial_view(meta, cameras).__dict__
        meta["title"] = title
        meta["alpha_threshold"] = alpha_threshold  # forced alpha blending tau (paper Sec. 3.4), None: off
        files = {
            "/": ("text/html; charset=utf-8", PAGE.encode("utf-8")),
            "/index.html": ("text/html; charset=utf-8", PAGE.encode("utf-8")),
            "/meta.json": ("application/json", json.dumps(meta).encode("utf-8")),
            "/splats.bin": ("application/octet-stream", payload),
        }

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 - the name http.server dispatches to
                path = self.path.split("?", 1)[0]
                if path not in files:
                    self.send_error(404, "not found")
                    return
                kind, body = files[path]
                self.send_response(200)
                self.send_header("Content-Type", kind)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, format: str, *args: object) -> None:  # noqa: A002 - signature of the base class
                # One line per request would bury the URL the user needs; requests are not logged.
                return None

        try:
            self.httpd = ThreadingHTTPServer((host, port), Handler)
        except OSError as err:
            raise SurfSplatInputError(f"--port {port}: cannot listen on {host}:{port} ({err.strerror})") from None
        self.meta = meta
        self.thread: threading.Thread | None = None

    @classmethod
    def from_ply(
        cls,
        path: str | Path,
        host: str = "127.0.0.1",
        port: int = 8080,
        cameras_path: str | Path | None = None,
        max_splats: int = 300_000,
        alpha_threshold: float | None | str = "auto",
    ) -> ViewerServer:
        """A server for a PLY; the reconstruction's cameras.json beside it (or `cameras_path`) sets the
        first view, and its reconstruction.json the forced-alpha-blending tau ("auto"; else 0.001)."""
        from ..export.paths import load_cameras
        from ..export.ply import load_ply

        path = Path(path)
        gaussians = load_ply(path)
        beside = path.parent / "cameras.json"
        cams_file = Path(cameras_path) if cameras_path is not None else (beside if beside.is_file() else None)
        cameras = load_cameras(cams_file).cameras if cams_file is not None else None
        if alpha_threshold == "auto":
            alpha_threshold = 0.001
            summary = path.parent / "reconstruction.json"
            if summary.is_file():
                try:
                    alpha_threshold = json.loads(summary.read_text()).get("alpha_threshold", 0.001)
                except ValueError:
                    raise SurfSplatInputError(f"{summary}: not valid JSON") from None
        return cls(
            gaussians, host, port, cameras, title=path.name, max_splats=max_splats, alpha_threshold=alpha_threshold
        )

    @property
    def url(self) -> str:
        host, port = self.httpd.server_address[:2]
        return f"http://{host}:{port}/"

    def start(self) -> ViewerServer:
        self.thread = threading.Thread(target=self.httpd.serve_forever, name="surfsplat-viewer", daemon=True)
        self.thread.start()
        return self

    def shutdown(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        if self.thread is not None:
            self.thread.join(timeout=5)
