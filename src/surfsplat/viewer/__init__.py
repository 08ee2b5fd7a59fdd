"""The browser viewer of `surfsplat view`, built on viser (its web client ships inside the wheel, so
it works offline).

    viewer = SurfelViewer(host="127.0.0.1", port=8080)
    viewer.show(load_viewer_scene("out/", viewer.progress))    # a PLY, or a reconstruction folder
    print(viewer.url)                                           # viewer.stop() ends it

Surfels are drawn by viser's Gaussian splat node with their full covariance (thin third axis);
context cameras as frustums with their images, the camera path and the mesh can be toggled; the
"Exact render" panel renders the browser's view with `surfsplat.render`.
"""

from .app import BrowserView, SurfelViewer, camera_view, view_cameras
from .scene import SplatArrays, ViewerScene, load_viewer_scene, splat_arrays

__all__ = [
    "BrowserView",
    "SplatArrays",
    "SurfelViewer",
    "ViewerScene",
    "camera_view",
    "load_viewer_scene",
    "splat_arrays",
    "view_cameras",
]
