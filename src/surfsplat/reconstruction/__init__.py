"""From any capture to one scene: `reconstruct(images | folder | video) -> Scene`.

    import surfsplat
    scene = surfsplat.reconstruct(["a.jpg", "b.jpg"], checkpoint="tiny-synthetic")
    scene.render(scale=2)
    scene.save("out/")

`surfsplat reconstruct` is this call and `Scene.save`.
"""

from .inputs import CaptureInput, read_capture
from .pipeline import CaptureOptions, reconstruct
from .scene import HeldOut, Scene

__all__ = ["CaptureInput", "CaptureOptions", "HeldOut", "Scene", "read_capture", "reconstruct"]
