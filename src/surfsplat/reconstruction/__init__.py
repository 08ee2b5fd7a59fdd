"""From any capture to one scene: `reconstruct(images | folder | video) -> Scene`.

    import surfsplat
    scene = surfsplat.reconstruct(["a.jpg", "b.jpg"], checkpoint="tiny-synthetic")
    scene.render(scale=2)
    scene.save("out/")

`surfsplat reconstruct` is this call and `Scene.save`; `surfsplat optimize` is `optimize_saved`.
"""

from .inputs import CaptureInput, read_capture
from .pipeline import CaptureOptions, reconstruct
from .scene import HeldOut, Scene
from .scene_fit import load_reconstruction, optimize_saved, optimize_scene

__all__ = [
    "CaptureInput",
    "CaptureOptions",
    "HeldOut",
    "Scene",
    "load_reconstruction",
    "optimize_saved",
    "optimize_scene",
    "read_capture",
    "reconstruct",
]
