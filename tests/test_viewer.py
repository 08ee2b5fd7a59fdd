"""The localhost viewer: exact splat packing, the HTTP routes, and the page in headless Chromium."""

from __future__ import annotations

import json
import shutil
import subprocess
import urllib.error
import urllib.request

import numpy as np
import pytest

from surfsplat.checks import SurfSplatInputError
from surfsplat.export.ply import save_ply
from surfsplat.geometry.sh import SH_C0
from surfsplat.scenes import make_scene
from surfsplat.viewer import ViewerServer, splat_buffer

CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)


@pytest.fixture(scope="module")
def scene():
    return make_scene(resolution=32)


def test_splat_buffer_packs_position_colour_opacity_radius(scene):
    g = scene.gaussians
    payload, meta = splat_buffer(g)
    data = np.frombuffer(payload, dtype="<f4").reshape(-1, 8)
    assert meta["count"] == meta["total"] == len(g) == data.shape[0]
    np.testing.assert_array_equal(data[:, :3], g.means.numpy().astype(np.float32))
    rgb = (0.5 + SH_C0 * g.sh[:, :, 0].double()).clamp(0, 1).numpy()
    np.testing.assert_allclose(data[:, 3:6], rgb, rtol=0, atol=1e-7)
    np.testing.assert_allclose(data[:, 6], g.opacities.numpy(), rtol=0, atol=1e-7)
    np.testing.assert_allclose(data[:, 7], g.scales.amax(-1).numpy(), rtol=1e-6, atol=0)


def test_splat_buffer_subsamples_deterministically(scene):
    a, meta = splat_buffer(scene.gaussians, max_splats=100)
    b, _ = splat_buffer(scene.gaussians, max_splats=100)
    assert meta["count"] == 100 and meta["total"] == len(scene.gaussians) and a == b
    rows = np.frombuffer(a, dtype="<f4").reshape(-1, 8)[:, :3]
    means = scene.gaussians.means.numpy().astype(np.float32)
    assert all((means == r).all(1).any() for r in rows[:10])  # real surfels, not new points
    with pytest.raises(SurfSplatInputError, match="max_splats"):
        splat_buffer(scene.gaussians, max_splats=0)


def test_server_routes(scene):
    server = ViewerServer(scene.gaussians, port=0, cameras=scene.sources).start()
    try:
        page = urllib.request.urlopen(server.url, timeout=30).read().decode()
        assert '<canvas id="view">' in page and "http" not in page.split("<script>")[1]  # nothing fetched from outside
        meta = json.loads(urllib.request.urlopen(server.url + "meta.json", timeout=30).read())
        assert meta["count"] == len(scene.gaussians)
        # The first view is the first source camera, looking along its axis.
        assert meta["camera"]["position"] == pytest.approx(scene.sources.c2w[0, :3, 3].tolist(), abs=1e-6)
        body = urllib.request.urlopen(server.url + "splats.bin", timeout=30).read()
        assert len(body) == meta["count"] * 8 * 4
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(server.url + "secret.txt", timeout=30)
        assert err.value.code == 404
    finally:
        server.shutdown()


def test_port_in_use_is_one_clear_error(scene):
    first = ViewerServer(scene.gaussians, port=0).start()
    try:
        port = first.httpd.server_address[1]
        with pytest.raises(SurfSplatInputError, match=f"--port {port}: cannot listen"):
            ViewerServer(scene.gaussians, port=port)
    finally:
        first.shutdown()


@pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium is not installed (apt-get install chromium)")
def test_page_draws_the_splats_in_headless_chromium(tmp_path, scene):
    ply = save_ply(scene.gaussians, tmp_path / "surfels.ply")
    server = ViewerServer.from_ply(ply, port=0).start()
    common = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--window-size=480,360",
        "--virtual-time-budget=10000",
    ]
    try:
        dom = subprocess.run([*common, "--dump-dom", server.url], capture_output=True, text=True, timeout=180)
        shot = subprocess.run(
            [*common, f"--screenshot={tmp_path / 'shot.png'}", server.url], capture_output=True, text=True, timeout=180
        )
    finally:
        server.shutdown()
    assert dom.returncode == 0, dom.stderr[-500:]
    assert 'data-state="ready"' in dom.stdout, dom.stdout[:500]
    drawn = int(dom.stdout.split('data-splats="')[1].split('"')[0])
    assert drawn > 0.5 * len(scene.gaussians)  # most surfels are in front of the source camera
    assert shot.returncode == 0, shot.stderr[-500:]
    import imageio.v3 as iio

    pixels = iio.imread(tmp_path / "shot.png").astype(np.float64)
    # The splats (sphere and backdrop colours) cover the canvas: many distinct colours, not a blank page.
    assert pixels[..., :3].std() > 20
    assert len(np.unique(pixels[..., :3].reshape(-1, 3).astype(np.uint8), axis=0)) > 1000
