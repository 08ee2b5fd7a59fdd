"""The viser viewer: the scene nodes it sends (surfels with their PLY covariances, frustums, path,
mesh), the camera convention between viser and `surfsplat.Cameras`, the exact-render panel, bad
input, and what a person sees in headless Chromium."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from plyfile import PlyData
from scipy.spatial.transform import Rotation

from surfsplat import Gaussians
from surfsplat.data.cameras import save_cameras
from surfsplat.data.synthetic.surfel_scene import SPHERE_CENTER, make_scene
from surfsplat.export.images import to_uint8
from surfsplat.export.mesh import Mesh, save_mesh
from surfsplat.export.paths import interpolate_cameras
from surfsplat.export.ply import save_ply
from surfsplat.render import render
from surfsplat.render.supersample import zoom_plan
from surfsplat.utils.checks import SurfSplatInputError
from surfsplat.viewer import BrowserView, SurfelViewer, camera_view, load_viewer_scene, splat_arrays, view_cameras
from surfsplat.viewer.app import set_client_view

RES = 24  # source views of the procedural scene: 2 x 24^2 = 1,152 surfels


@pytest.fixture(scope="module")
def scene():
    return make_scene(resolution=RES)


@pytest.fixture(scope="module")
def output_dir(scene, tmp_path_factory):
    """A folder laid out as `surfsplat reconstruct` writes it (made directly, without a model)."""
    out = tmp_path_factory.mktemp("reconstruction")
    save_ply(scene.gaussians, out / "surfels.ply")
    save_cameras(out / "cameras.json", scene.sources, RES, RES, ["left.png", "right.png"])
    ramp = np.linspace(0, 255, RES, dtype=np.uint8)
    iio.imwrite(out / "left.png", np.stack([np.tile(ramp, (RES, 1))] * 3, -1))  # the input photo of view 0
    (out / "renders").mkdir()
    iio.imwrite(out / "renders" / "view01_color.png", np.full((RES, RES, 3), 200, np.uint8))  # view 1: a render
    tetra = torch.tensor([[0, 0, 5.0], [1, 0, 5], [0, 1, 5], [0, 0, 6]])
    faces = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    save_mesh(
        Mesh(tetra, faces, torch.nn.functional.normalize(tetra, dim=1), torch.full((4, 3), 0.5)), out / "mesh.ply"
    )
    summary = {"alpha_threshold": 0.001, "images": ["left.png", "missing/right.png"], "render_mode": "surfel"}
    (out / "reconstruction.json").write_text(json.dumps(summary))
    return out


@pytest.fixture(scope="module")
def viewer(output_dir):
    v = SurfelViewer(port=0)
    v.show(load_viewer_scene(output_dir, v.progress))
    yield v
    v.stop()


def ply_covariances(path) -> np.ndarray:
    """[N, 3, 3] covariances straight from the PLY columns (scipy's quaternion, x y z w order):
    R diag(exp(scale_0)^2, exp(scale_1)^2, 0) R^T, the surfel's thin third axis."""
    v = PlyData.read(str(path))["vertex"]
    q = np.stack([v["rot_1"], v["rot_2"], v["rot_3"], v["rot_0"]], -1).astype(np.float64)
    R = Rotation.from_quat(q).as_matrix()
    var = np.stack([np.exp(2.0 * v["scale_0"]), np.exp(2.0 * v["scale_1"]), np.zeros(len(q))], -1)
    return (R * var[:, None, :]) @ R.transpose(0, 2, 1)


def test_scene_nodes_hold_the_ply_surfels_cameras_path_and_mesh(viewer, output_dir, scene):
    splats = viewer.splats
    n = len(scene.gaussians)
    unit = float(splats.scale)
    assert splats.centers.shape == (n, 3)
    np.testing.assert_allclose(splats.centers * unit, scene.gaussians.means.numpy(), rtol=1e-6, atol=1e-6)
    # viser carries covariances as float16 (11 significant bits): equal to the PLY's at that precision.
    expected = ply_covariances(output_dir / "surfels.ply")
    sent = splats.covariances.astype(np.float64) * unit**2
    biggest = np.abs(expected).reshape(n, -1).max(1)[:, None, None]
    assert np.abs(sent - expected).max() > 0  # it is the float16 copy, not the input array
    assert (np.abs(sent - expected) / biggest).max() < 2e-3
    # The thin third axis: one eigenvalue ~0, the other two the squared tangent scales.
    evals = np.linalg.eigvalsh(sent)
    scales = scene.gaussians.scales.double().numpy()
    np.testing.assert_allclose(np.sqrt(np.clip(evals[:, 1:], 0, None)), np.sort(scales, 1), rtol=2e-3)
    assert np.abs(evals[:, 0]).max() < 1e-3 * evals[:, 2].min()
    # Colour: the SH DC term through 0.5 + C0 * dc, opacity as stored, both as bytes.
    v = PlyData.read(str(output_dir / "surfels.ply"))["vertex"]
    dc = np.stack([v[f"f_dc_{c}"] for c in range(3)], -1).astype(np.float64)
    rgb = np.clip(0.28209479177387814 * dc + 0.5, 0, 1)
    assert np.abs(splats.rgbs.astype(np.float64) - rgb * 255).max() <= 1
    opacity = 1 / (1 + np.exp(-np.asarray(v["opacity"], np.float64)))
    assert np.abs(splats.opacities[:, 0].astype(np.float64) - opacity * 255).max() <= 1

    # One frustum per context camera, where the camera is, with the photo (view 0) or the render (view 1).
    assert len(viewer.frustums) == 2
    for i, frustum in enumerate(viewer.frustums):
        c2w = scene.sources.c2w[i].double().numpy()
        np.testing.assert_allclose(frustum.position, c2w[:3, 3], atol=1e-6)
        R = Rotation.from_quat(np.roll(np.asarray(frustum.wxyz), -1)).as_matrix()
        np.testing.assert_allclose(R, c2w[:3, :3], atol=1e-6)
        assert frustum.fov == pytest.approx(2 * np.arctan(RES / 2 / float(scene.sources.K[i, 1, 1])))
    photo = viewer.frustums[0].image
    assert photo.shape == (RES, RES, 3) and photo[0, 0, 0] == 0 and photo[0, -1, 0] == 255
    assert (viewer.frustums[1].image == 200).all()
    # The camera path is the interpolation the video follows; the mesh is the file's.
    path = interpolate_cameras(scene.sources, 48)
    line = viewer.path_nodes[0]
    np.testing.assert_allclose(line.points, path.centers.double().numpy(), atol=1e-6)
    assert viewer.mesh.faces.shape == (4, 3) and viewer.mesh.vertices.shape == (4, 3)
    assert viewer.mesh.visible is False  # off until toggled: it would hide the splats
    assert set(viewer.groups) == {"Surfels", "Context cameras", "Camera path", "Mesh"}
    assert viewer.scene.alpha_threshold == 0.001 and viewer.scene.mode == "surfel"


def test_loading_reports_its_progress(output_dir):
    steps: list[tuple[str, float]] = []
    load_viewer_scene(output_dir, lambda what, fraction: steps.append((what, fraction)))
    whats = [what for what, _ in steps]
    assert whats[0] == "reading surfels.ply" and "reading cameras.json" in whats and "reading mesh.ply" in whats
    fractions = [fraction for _, fraction in steps]
    assert fractions == sorted(fractions) and fractions[0] == 0 and fractions[-1] == 1


def test_a_ply_alone_shows_only_its_surfels(output_dir):
    scene = load_viewer_scene(output_dir / "surfels.ply")
    assert scene.cameras is None and scene.path is None and scene.mesh is None and len(scene.images) == 0


def test_a_3dgs_layout_ply_keeps_its_own_covariances(scene, tmp_path):
    g = scene.gaussians
    R = g.rotations.double()
    fat = (R * torch.tensor([1.0, 0.25, 0.04], dtype=torch.float64).mul(g.scales[:, :1].double() ** 2)[:, None]) @ R.mT
    path = save_ply(g.with_explicit_covariances(fat.float()), tmp_path / "gaussians_3dgs.ply")
    loaded = load_viewer_scene(path)
    arrays = splat_arrays(loaded.gaussians)
    assert loaded.mode == "ewa"
    np.testing.assert_allclose(
        arrays.covariances * arrays.unit**2, fat.numpy(), rtol=0, atol=1e-6 * float(fat.abs().max())
    )


def test_float16_covariances_of_a_millimetre_scene_keep_their_shape(scene):
    """viser packs covariances as float16 (normal range from 6e-5): the node's unit keeps tiny surfels."""
    g = scene.gaussians
    tiny = Gaussians(g.means * 1e-3, g.quats, g.scales * 1e-3, g.opacities, g.sh)
    arrays = splat_arrays(tiny)
    cov = tiny.covariances.double().numpy()
    biggest = np.abs(cov).reshape(len(cov), -1).max(1)[:, None, None]
    packed = arrays.covariances.astype(np.float16).astype(np.float64) * arrays.unit**2
    assert (np.abs(packed - cov) / biggest).max() < 2e-3
    raw = cov.astype(np.float16).astype(np.float64)  # what sending world units would lose
    assert (np.abs(raw - cov) / biggest).max() > 0.1


def test_convention_browser_view_is_opencv_c2w_with_vertical_fov(scene):
    """A camera's browser view converts back to the same c2w and K; the view's look direction is
    its +z column and the top of the image is -y (OpenCV), as viser's camera handle documents."""
    view = camera_view(scene.sources, 1, RES, RES)
    cams, width, height = view_cameras(view, RES)
    assert (width, height) == (RES, RES)
    torch.testing.assert_close(cams.c2w[0], scene.sources.c2w[1].double(), atol=1e-6, rtol=0)
    torch.testing.assert_close(cams.K[0], scene.sources.K[1].double(), atol=1e-4, rtol=0)
    # A browser looking from the origin at +x, up +z: the point ahead lands at the image centre,
    # a point above it in the upper half, a point to its right (-y when facing +x with z up) on the right.
    R = np.stack([[0.0, -1, 0], [0, 0, -1], [1, 0, 0]], axis=1)  # columns: right, down, forward
    wxyz = np.roll(Rotation.from_matrix(R).as_quat(), 1)
    cams, w, h = view_cameras(BrowserView(tuple(wxyz), (0.0, 0.0, 0.0), np.radians(60), 2.0), 100)
    assert (w, h) == (200, 100) and float(cams.K[0, 1, 1]) == pytest.approx(50 / np.tan(np.radians(30)))

    def pixel(point):
        p = cams.K[0] @ (cams.w2c[0, :3, :3] @ torch.tensor(point, dtype=torch.float64) + cams.w2c[0, :3, 3])
        return (p[:2] / p[2]).tolist()

    assert pixel([5.0, 0, 0]) == pytest.approx([100, 50])
    assert pixel([5.0, 0, 1])[1] < 50 and pixel([5.0, -1, 0])[0] > 100


def test_exact_render_is_the_renderer_at_the_browser_view(viewer, scene):
    view = camera_view(scene.sources, 0, RES, RES)
    browser, _, _ = view_cameras(view, RES)
    for factor in (1, 2):
        image = viewer.render_view(view, factor, "image")
        # Exactly the renderer at the browser's camera, of the surfels the viewer read, at the zoom the
        # scene was made at (x2: with the filter of its own pixels) ...
        shown = viewer.scene.gaussians
        cams = browser.scaled(factor).to(shown.means.dtype)
        fitted = (viewer.scene.cameras, viewer.scene.width, viewer.scene.height)
        plan = zoom_plan(shown, *fitted, cams, RES * factor, RES * factor)
        assert plan.supersample == 1 and plan.filter_zoom == pytest.approx(factor, rel=1e-2)
        truth = render(shown, cams, RES * factor, RES * factor, alpha_threshold=0.001, filter_zoom=plan.filter_zoom)
        np.testing.assert_array_equal(image, to_uint8(truth.color[0]))
        # ... which is the source scene and camera up to the PLY's and the view's float rounding
        # (1e-7): float32 compositing may move a colour across a uint8 step at a few pixels, no further.
        source = render(
            scene.gaussians,
            scene.sources[0].scaled(factor),
            RES * factor,
            RES * factor,
            alpha_threshold=0.001,
            filter_zoom=plan.filter_zoom,
        )
        step = np.abs(image.astype(int) - to_uint8(source.color[0]).astype(int))
        assert step.max() <= 1 and (step > 0).mean() < 1e-3
    depth = viewer.render_view(view, 1, "depth")
    normal = viewer.render_view(view, 1, "normal")
    assert depth.shape == normal.shape == (RES, RES, 3)
    # Depth colours: the sphere (near) and the backdrop (far) map to different ends of the ramp.
    assert np.abs(depth[RES // 2, RES // 2].astype(int) - depth[1, 1].astype(int)).sum() > 100
    # Normals face the camera (-z) at the sphere's centre: rgb = n / 2 + 0.5 has blue near 0.
    assert normal[RES // 2, RES // 2, 2] < 40
    viewer.show_render(depth, "depth at x1")
    assert viewer.render_image.visible and np.array_equal(viewer.last_render, depth)
    with pytest.raises(SurfSplatInputError, match="output"):
        viewer.render_view(view, 1, "albedo")


def test_not_our_ply_or_a_broken_one_is_one_clear_error(output_dir, tmp_path):
    with pytest.raises(SurfSplatInputError, match="not a Gaussian-splat PLY, missing vertex properties"):
        load_viewer_scene(output_dir / "mesh.ply")
    broken = tmp_path / "broken.ply"
    broken.write_bytes((output_dir / "surfels.ply").read_bytes()[:3000])
    with pytest.raises(SurfSplatInputError, match="broken.ply: not a readable PLY"):
        load_viewer_scene(broken)
    values = PlyData.read(str(output_dir / "surfels.ply"))
    values["vertex"].data["x"][5] = np.nan
    values.write(str(tmp_path / "nan.ply"))
    with pytest.raises(SurfSplatInputError, match="nan.ply: vertex property .x. holds NaN"):
        load_viewer_scene(tmp_path / "nan.ply")
    with pytest.raises(SurfSplatInputError, match="no surfels.ply"):
        load_viewer_scene(tmp_path)
    # The command: exit code 2, one line naming the file, no traceback, no server left running.
    done = subprocess.run(
        [sys.executable, "-m", "surfsplat", "view", str(broken), "--port", "0"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"surfsplat view: error: {broken}: not a readable PLY file"), lines


def test_listens_on_localhost_by_default_and_checks_the_address(viewer):
    from surfsplat.cli import build_parser

    assert viewer.url.startswith("http://127.0.0.1:")
    # A share URL (a public tunnel) asked for by a websocket client is refused without any connection.
    assert viewer.server.request_share_url() is None and viewer.server._share_tunnel is None

    args = build_parser().parse_args(["view", "x.ply"])
    assert args.host == "127.0.0.1"
    with pytest.raises(SurfSplatInputError, match="--port"):
        SurfelViewer(port=70000)
    with pytest.raises(SurfSplatInputError, match="--host 203.0.113.7: cannot listen"):
        SurfelViewer(host="203.0.113.7", port=0)


def _wait(condition, timeout: float = 40.0) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


@pytest.mark.slow
def test_headless_chromium_draws_the_splats(viewer, scene, tmp_path):
    """What a person sees, in Chromium with software WebGL: the splats over most of the view; the
    render button and "look through" working for a real browser; another pose showing something
    else; and the WebGL preview agreeing with the exact render of the camera the browser reports
    (which pins viser's camera convention to ours)."""
    from tests.helpers.browser import Browser, chromium

    exe = chromium()
    clients: list = []
    reported: list[BrowserView] = []

    @viewer.server.on_client_connect
    def _(client) -> None:
        clients.append(client)

        @client.camera.on_update
        def _(camera) -> None:
            reported.append(BrowserView(tuple(camera.wxyz), tuple(camera.position), float(camera.fov), camera.aspect))

    def at(position) -> bool:
        return bool(reported) and np.allclose(reported[-1].position, position, atol=1e-5)

    width, height = 800, 600
    region = (slice(170, height), slice(0, 450))  # the 3D view left of the panel, below the WebGL notice

    def drawn(image: np.ndarray) -> np.ndarray:
        background = image[height - 5, 5].astype(int)  # a corner the splats do not reach
        return np.abs(image[region].astype(int) - background).sum(-1) > 30

    with Browser(exe, viewer.url, width, height) as browser:
        initial = viewer.server.initial_camera
        assert _wait(lambda: at(initial.position), 90), "the page never took its initial camera"
        first = browser.wait_for(lambda image: drawn(image).mean() > 0.25)
        iio.imwrite(tmp_path / "initial.png", first)
        covered = drawn(first)
        assert covered.mean() > 0.25, f"splats cover {covered.mean():.0%} of the view"
        assert len({tuple(p) for p in first[region][covered][::7]}) > 300  # textured colours, not a flat fill

        # "Render this view": the exact render of the browser's view, shown in the panel.
        (client,) = clients
        viewer.render_for_client(client)
        assert np.array_equal(viewer.last_render, viewer.render_view(reported[-1], 1, "image"))
        assert viewer.render_image.visible and viewer.render_info.content.startswith("image at x1")

        # "Look through" camera 1 (what a click on its frustum does): the browser is at that camera.
        looked = camera_view(scene.sources, 1, RES, RES)
        set_client_view(client, looked)
        assert _wait(lambda: at(looked.position))
        view = reported[-1]
        assert view.fov == pytest.approx(looked.fov) and abs(np.dot(view.wxyz, looked.wxyz)) == pytest.approx(1)

        # A side view of the sphere with the splats alone, in WebGL and in the exact renderer.
        for name in ("Context cameras", "Camera path"):
            viewer.toggles[name].value = False  # as a click on the panel's checkbox
            assert viewer.groups[name].visible is False
        side = (2.2, -0.8, 1.2)
        with client.atomic():
            client.camera.position = side
            client.camera.look_at = SPHERE_CENTER
        assert _wait(lambda: at(side))
        # The splats are in; the camera has moved (it reported so): no fade to wait for.
        second = browser.wait_for(lambda image: drawn(image).mean() > 0.25, settle=0.5, steady=False)
        iio.imwrite(tmp_path / "side.png", second)
        view = reported[-1]
    changed = np.abs(second[region].astype(int) - first[region].astype(int)).sum(-1) > 30
    assert changed.mean() > 0.2, f"two poses differ on {changed.mean():.0%} of the view"
    for name in ("Context cameras", "Camera path"):
        viewer.toggles[name].value = True

    cams, rw, rh = view_cameras(view, height)
    assert (rw, rh) == (width, height)
    # The browser looks at the point it was told to, with the scene's up at the top of the image.
    to_target = np.asarray(SPHERE_CENTER) - np.asarray(view.position)
    assert cams.c2w[0, :3, 2].numpy() @ (to_target / np.linalg.norm(to_target)) > 1 - 1e-6
    assert -cams.c2w[0, :3, 1].numpy() @ np.asarray(initial.up) > 0.5
    exact = render(scene.gaussians, cams.to(torch.float32), rw, rh, background=(1.0, 1.0, 1.0))
    iio.imwrite(tmp_path / "side_exact.png", to_uint8(exact.color[0]))
    webgl_mask = drawn(second)
    exact_mask = exact.alpha[0, 0].numpy()[region] > 0.5
    iou = (webgl_mask & exact_mask).sum() / (webgl_mask | exact_mask).sum()
    assert iou > 0.8, f"WebGL and exact render silhouettes overlap by IoU {iou:.2f}"
