"""A browser viewer for surfels on localhost: a small HTTP server and one self-contained page.

    server = ViewerServer.from_ply("out/surfels.ply", port=8080).start()
    print(server.url)            # open it in a browser; server.shutdown() stops it

The page (`surfsplat.viewer.page`) draws the surfels with a Canvas 2D splatting rasterizer written
in plain JavaScript: no WebGL, no script or font from the network, so it works offline and in
headless browsers.
"""

from .server import ViewerServer, splat_buffer

__all__ = ["ViewerServer", "splat_buffer"]
