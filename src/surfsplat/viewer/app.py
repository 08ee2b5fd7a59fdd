"""The viewer on viser: surfels as Gaussian splats, cameras, camera path, mesh and an exact render.

    viewer = SurfelViewer(port=8080)                       # the page is up (showing progress) at once
    viewer.show(load_viewer_scene("out/", viewer.progress))
    print(viewer.url); ...; viewer.stop()

The browser previews the surfels with viser's WebGL splatting (each surfel's full 3D covariance
projected by the affine EWA approximation, sorted per frame); "Exact render" renders the browser's
current viewpoint with `surfsplat.render` (ray-splat intersection, forced alpha blending), so the
difference between the preview and the true 2DGS image is one click away.

Camera convention: viser's cameras are OpenCV-like (x right, y down, z forward; `wxyz` and
`position` give R and t of P_world = R p_camera + t; `fov` is vertical), the same axes as
`surfsplat.Cameras`' c2w, so the conversion is only a quaternion and a pinhole K.
"""

from __future__ import annotations

import io
import ipaddress
import logging
import math
import socket
import threading
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from ..geometry.cameras import Cameras
from ..utils.checks import SurfSplatInputError
from .scene import ViewerScene, scene_bounds, splat_arrays, summary_line

logger = logging.getLogger(__name__)

SCALES = {"x1": 1, "x2": 2, "x4": 4}  # exact-render resolution factors (HRRC's x1/x2/x4)
Output = Literal["image", "depth", "normal"]
OUTPUTS: tuple[Output, ...] = ("image", "depth", "normal")
DEFAULT_RENDER_HEIGHT = 256  # x1 height of the exact render when the scene has no cameras to take it from
CAMERA_COLOR = (220, 80, 40)  # context frustums
PATH_COLOR = (40, 110, 220)  # the camera path and its frames
PATH_FRUSTUMS = 8  # frames of the path drawn as small frustums (the line shows the rest)


@dataclass(frozen=True)
class BrowserView:
    """A viewpoint as viser reports a browser's camera."""

    wxyz: tuple[float, float, float, float]  # rotation camera -> world (OpenCV camera axes)
    position: tuple[float, float, float]  # camera centre in the world
    fov: float  # vertical field of view, radians
    aspect: float  # width / height of the browser's canvas


def view_cameras(view: BrowserView, height: int) -> tuple[Cameras, int, int]:
    """The pinhole camera of a browser view for an image `height` pixels tall: (cameras [1], width, height).

    Square pixels, principal point at the image centre, fy = (H / 2) / tan(fov / 2).
    """
    from viser import transforms as vtf

    if not (0 < view.fov < math.pi and view.aspect > 0 and height >= 1):
        raise SurfSplatInputError(f"browser view: expected 0 < fov < pi, aspect > 0, got {view.fov}, {view.aspect}")
    width = max(1, round(height * view.aspect))
    f = (height / 2) / math.tan(view.fov / 2)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = torch.from_numpy(vtf.SO3(np.asarray(view.wxyz, dtype=np.float64)).as_matrix())
    c2w[:3, 3] = torch.tensor(view.position, dtype=torch.float64)
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float64)
    return Cameras(c2w[None], K[None]), width, height


def camera_view(cameras: Cameras, index: int, width: int, height: int) -> BrowserView:
    """The browser view of camera `index` of images width x height (the inverse of `view_cameras`
    for square pixels and a centred principal point)."""
    from viser import transforms as vtf

    c2w = cameras.c2w[index].detach().to("cpu", torch.float64).numpy()
    fy = float(cameras.K[index, 1, 1])
    wxyz = vtf.SO3.from_matrix(c2w[:3, :3]).wxyz
    return BrowserView(
        tuple(map(float, wxyz)), tuple(map(float, c2w[:3, 3])), 2 * math.atan(height / (2 * fy)), width / height
    )


def check_listen_address(host: str, port: int) -> None:
    """One clear error before viser starts: it would otherwise retry other ports on any OSError."""
    if not 0 <= port <= 65535:
        raise SurfSplatInputError(f"--port: expected 0..65535, got {port}")
    try:
        family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0][0]
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.bind((host, 0))
    except OSError as err:
        raise SurfSplatInputError(f"--host {host}: cannot listen there ({err.strerror or err})") from None


def _is_loopback(host: str) -> bool:
    """Whether `host` names this machine only (127.0.0.0/8, ::1, localhost)."""
    try:
        infos = socket.getaddrinfo(host, None)
    except OSError:
        return False
    return all(ipaddress.ip_address(info[4][0].split("%")[0]).is_loopback for info in infos)


def _no_share_url(verbose: bool = True) -> None:
    """In place of viser's share-URL request: no tunnel."""
    return None


def set_client_view(client, view: BrowserView) -> None:
    """Move one browser's camera to `view` (its fov too; the canvas keeps its own aspect)."""
    with client.atomic():
        client.camera.wxyz = view.wxyz
        client.camera.position = view.position
        client.camera.fov = view.fov


class SurfelViewer:
    """A viser server showing one scene. The page is up, with a progress bar, from construction;
    `show` fills it."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, title: str = "surfsplat") -> None:
        import viser

        check_listen_address(host, port)
        if not _is_loopback(host):
            logger.warning(
                "--host %s: the viewer is reachable from other machines; anyone who can reach this port sees the scene",
                host,
            )
        self.host = host
        self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        # viser can open a public tunnel ("share URL") when any websocket client asks, and a web page
        # from any site can open a websocket to localhost: hide the button and refuse the request, so
        # the scene never leaves this machine.
        self.server.gui.configure_theme(show_share_button=False, show_logo=False, control_width="medium")
        self.server.request_share_url = _no_share_url
        self.scene: ViewerScene | None = None
        self.splats = None  # viser GaussianSplatHandle
        self.frustums: list = []  # context cameras, one handle each
        self.path_nodes: list = []  # the path's line and its frames
        self.mesh = None
        self.groups: dict[str, object] = {}  # toggle name -> scene node whose visibility it switches
        self.toggles: dict[str, object] = {}  # toggle name -> its checkbox in the panel
        self.last_render: np.ndarray | None = None  # [H, W, 3] uint8 of the last exact render
        self._render_lock = threading.Lock()
        self._status = self.server.gui.add_markdown("**Loading the scene...**")
        self._bar = self.server.gui.add_progress_bar(0.0, animated=True)

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.server.get_port()}/"

    def progress(self, what: str, fraction: float) -> None:
        """Shown in the page while the scene loads."""
        self._status.content = f"**Loading:** {what}"
        self._bar.value = 100.0 * min(max(fraction, 0.0), 1.0)

    def stop(self) -> None:
        self.server.stop()

    # ------------------------------------------------------------------------------------ the scene
    def show(self, scene: ViewerScene) -> None:
        """Send the scene to the browsers and build the panel."""
        self.scene = scene
        nodes = self.server.scene
        center, radius = scene_bounds(scene.gaussians)
        self.progress(f"sending {len(scene.gaussians):,} surfels", 0.9)
        arrays = splat_arrays(scene.gaussians)
        self.splats = nodes.add_gaussian_splats(
            "/surfels", arrays.centers, arrays.covariances, arrays.rgbs, arrays.opacities, scale=arrays.unit
        )
        self.groups["Surfels"] = self.splats
        frustum_size = 0.08 * radius
        if scene.cameras is not None:
            self.groups["Context cameras"] = nodes.add_frame("/cameras", show_axes=False)
            for i in range(len(scene.cameras)):
                view = camera_view(scene.cameras, i, scene.width, scene.height)
                self.frustums.append(
                    nodes.add_camera_frustum(
                        f"/cameras/{i:02d}",
                        fov=view.fov,
                        aspect=view.aspect,
                        scale=frustum_size,
                        image=scene.images[i] if i < len(scene.images) else None,
                        wxyz=view.wxyz,
                        position=view.position,
                        color=CAMERA_COLOR,
                        thickness=2.0,
                        thickness_units="screen",
                    )
                )
                self.frustums[-1].on_click(lambda event, view=view: set_client_view(event.client, view))
        if scene.path is not None:
            self.groups["Camera path"] = nodes.add_frame("/camera_path", show_axes=False)
            centres = scene.path.centers.detach().to("cpu", torch.float64).numpy()
            self.path_nodes.append(
                nodes.add_spline_catmull_rom(
                    "/camera_path/line",
                    centres,
                    thickness=3.0,
                    thickness_units="screen",
                    color=PATH_COLOR,
                    curve_type="chordal",
                )
            )
            picks = np.unique(np.linspace(0, len(scene.path) - 1, PATH_FRUSTUMS).round().astype(int))
            for f in picks:
                view = camera_view(scene.path, int(f), scene.width, scene.height)
                self.path_nodes.append(
                    nodes.add_camera_frustum(
                        f"/camera_path/frame{f:03d}",
                        fov=view.fov,
                        aspect=view.aspect,
                        scale=0.5 * frustum_size,
                        wxyz=view.wxyz,
                        position=view.position,
                        color=PATH_COLOR,
                        thickness=1.5,
                        thickness_units="screen",
                    )
                )
        if scene.mesh is not None:
            # Off at first: an opaque mesh would hide the splats it was fused from.
            self.mesh = nodes.add_mesh_simple(
                "/mesh", scene.mesh.vertices, scene.mesh.faces, color=(190, 190, 180), side="double", visible=False
            )
            self.groups["Mesh"] = self.mesh

        # Start behind the first context camera (looking where it looks, the cameras' up as the world's
        # up), so its frustum and the path are in view; without cameras, from -z with y down (the
        # OpenCV world most captures are in).
        initial = self.server.initial_camera
        initial.near, initial.far = 1e-3 * radius, 1e3 * radius
        if scene.cameras is not None:
            c2w = scene.cameras.c2w.detach().to("cpu", torch.float64).numpy()
            up = -c2w[:, :3, 1].mean(0)
            up = up / max(np.linalg.norm(up), 1e-12)
            eye, forward = c2w[0, :3, 3], c2w[0, :3, 2]
            depth = max(float((center - eye) @ forward), 1e-3 * radius)
            target = eye + forward * depth
            eye = eye - forward * (0.6 * depth) + up * (0.2 * depth)
            fov = camera_view(scene.cameras, 0, scene.width, scene.height).fov
        else:
            up = np.array([0.0, -1.0, 0.0])
            eye, target, fov = center - np.array([0.0, 0.0, 2.5 * radius]), center, math.radians(50)
        nodes.set_up_direction(tuple(map(float, up)))
        initial.up = tuple(map(float, up))
        initial.position = tuple(map(float, eye))
        initial.look_at = tuple(map(float, target))
        initial.fov = fov
        self._build_panel(scene)
        self._bar.remove()
        self._status.content = f"**{scene.title}**: {summary_line(scene)}"

    def _build_panel(self, scene: ViewerScene) -> None:
        gui = self.server.gui
        with gui.add_folder("Show"):
            for name, node in self.groups.items():
                self.toggles[name] = gui.add_checkbox(name, initial_value=bool(node.visible))
                self.toggles[name].on_update(lambda event, node=node: setattr(node, "visible", event.target.value))
        if scene.cameras is not None:
            names = [f"{i:02d} {n}" for i, n in enumerate(scene.names)]
            views = {n: camera_view(scene.cameras, i, scene.width, scene.height) for i, n in enumerate(names)}
            pick = gui.add_dropdown("Look through", ("-", *names), initial_value="-", hint="or click a frustum")

            @pick.on_update
            def _(event) -> None:
                if event.client is not None and event.target.value in views:  # a browser's choice, for it
                    set_client_view(event.client, views[event.target.value])

        tau = "off" if scene.alpha_threshold is None else f"{scene.alpha_threshold:g}"
        with gui.add_folder("Exact render"):
            gui.add_markdown(
                f"Renders this view with surfsplat's {scene.mode} rasterizer (forced alpha blending "
                f"threshold {tau}, as the evaluation); the 3D view above is viser's WebGL preview."
            )
            self.scale_choice = gui.add_dropdown("Scale", tuple(SCALES), initial_value="x1")
            self.output_choice = gui.add_dropdown("Output", OUTPUTS, initial_value="image")
            button = gui.add_button("Render this view")
            button.on_click(lambda event: self.render_for_client(event.client))
            self.render_info = gui.add_markdown("")
            self.render_image = gui.add_image(np.zeros((1, 1, 3), np.uint8), format="png", visible=False)
            self.save_button = gui.add_button("Download the render (PNG)", visible=False)
            self.save_button.on_click(lambda event: self._send_png(event.client))

    # ------------------------------------------------------------------------------------ exact render
    def render_height(self) -> int:
        """x1 height: the reconstruction's image height, so x1/x2/x4 mean what they mean in HRRC."""
        return self.scene.height if self.scene is not None and self.scene.height else DEFAULT_RENDER_HEIGHT

    @torch.inference_mode()
    def render_view(self, view: BrowserView, scale: int = 1, output: Output = "image") -> np.ndarray:
        """The exact render of a browser view at `scale` times the x1 size: [H, W, 3] uint8."""
        from ..export.images import colorize_depth, normal_to_rgb, to_uint8
        from ..render import render
        from ..render.supersample import zoom_plan

        if self.scene is None:
            raise SurfSplatInputError("viewer: no scene shown yet")
        if output not in OUTPUTS:
            raise SurfSplatInputError(f"output: expected one of {OUTPUTS}, got {output!r}")
        cams, width, height = view_cameras(view, self.render_height())
        cams = cams.scaled(scale).to(self.scene.gaussians.means.dtype)
        scene = self.scene
        plan = zoom_plan(scene.gaussians, scene.cameras, scene.width, scene.height, cams, width * scale, height * scale)
        out = render(
            plan.gaussians,
            cams,
            width * scale,
            height * scale,
            mode=scene.mode,
            alpha_threshold=scene.alpha_threshold,
            antialiased=scene.antialiased,
            supersample=plan.supersample,  # zoomed out: drawn at the fitted zoom and averaged down
            filter_zoom=plan.filter_zoom,  # zoomed in: the fitted pixels' filter
        )
        if output == "image":
            return to_uint8(out.color[0])
        if output == "normal":
            return to_uint8(normal_to_rgb(out.normal[0]))
        # Depth counts where the render is opaque: alpha >= tau under forced alpha blending, else >= 0.5.
        tau = self.scene.alpha_threshold if self.scene.alpha_threshold is not None else 0.5
        return to_uint8(colorize_depth(out.depth[0], (out.alpha[0] >= tau).float()))

    def render_for_client(self, client) -> None:
        """What the panel's button does: render that browser's current view, show it in the panel."""
        cam = client.camera
        view = BrowserView(tuple(cam.wxyz), tuple(cam.position), float(cam.fov), float(cam.aspect))
        scale, output = SCALES[self.scale_choice.value], self.output_choice.value
        if not self._render_lock.acquire(blocking=False):
            client.add_notification("Busy", "A render is already running.", auto_close_seconds=3.0)
            return
        note = client.add_notification("Rendering", f"{output} at {self.scale_choice.value}", loading=True)
        try:
            start = time.perf_counter()
            image = self.render_view(view, scale, output)
            seconds = time.perf_counter() - start
            self.show_render(
                image, f"{output} at {self.scale_choice.value}: {image.shape[1]}x{image.shape[0]} px in {seconds:.2f} s"
            )
        finally:
            note.remove()
            self._render_lock.release()

    def show_render(self, image: np.ndarray, caption: str) -> None:
        self.last_render = image
        self.render_image.image = image
        self.render_image.visible = True
        self.save_button.visible = True
        self.render_info.content = caption

    def _send_png(self, client) -> None:
        import imageio.v3 as iio

        if self.last_render is None:
            return
        buffer = io.BytesIO()
        iio.imwrite(buffer, self.last_render, extension=".png")
        client.send_file_download("surfsplat_render.png", buffer.getvalue())
