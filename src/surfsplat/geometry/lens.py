"""Camera lenses as COLMAP names them: the record every reader, pose estimation and the undistortion share.

A `Lens` is a camera model with its calibrated image size and its parameters in COLMAP's own order
(`colmap/src/colmap/sensor/models.h`; pycolmap's `Camera.params_info` prints them). Every stage after
loading sees pinhole cameras (SPEC section 2): a capture with a lens is undistorted once, where it is
read, and the reconstruction records the lens it came from beside the pinhole it used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..utils.checks import SurfSplatInputError

# COLMAP's camera models: id -> (name, parameter names in COLMAP's order).
CAMERA_MODELS: dict[int, tuple[str, tuple[str, ...]]] = {
    0: ("SIMPLE_PINHOLE", ("f", "cx", "cy")),
    1: ("PINHOLE", ("fx", "fy", "cx", "cy")),
    2: ("SIMPLE_RADIAL", ("f", "cx", "cy", "k")),
    3: ("RADIAL", ("f", "cx", "cy", "k1", "k2")),
    4: ("OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    5: ("OPENCV_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
    6: ("FULL_OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
    7: ("FOV", ("fx", "fy", "cx", "cy", "omega")),
    8: ("SIMPLE_RADIAL_FISHEYE", ("f", "cx", "cy", "k")),
    9: ("RADIAL_FISHEYE", ("f", "cx", "cy", "k1", "k2")),
    10: ("THIN_PRISM_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1")),
}
MODEL_IDS: dict[str, int] = {name: i for i, (name, _) in CAMERA_MODELS.items()}
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")


@dataclass(frozen=True)
class Lens:
    """One camera's lens: COLMAP model name, the image size it was calibrated at, its parameters."""

    model: str  # a name of CAMERA_MODELS, e.g. "SIMPLE_RADIAL"
    width: int  # calibrated image size in pixels
    height: int
    params: tuple[float, ...]  # in COLMAP's order for the model

    def __post_init__(self) -> None:
        if self.model not in MODEL_IDS:
            known = ", ".join(name for name, _ in CAMERA_MODELS.values())
            raise SurfSplatInputError(f"camera model: unknown model {self.model!r} (known: {known})")
        names = CAMERA_MODELS[MODEL_IDS[self.model]][1]
        if len(self.params) != len(names):
            raise SurfSplatInputError(
                f"camera model {self.model}: expected {len(names)} parameters ({', '.join(names)}), "
                f"got {len(self.params)}"
            )
        bad = [n for n, v in zip(names, self.params) if not math.isfinite(v)]
        if bad:
            raise SurfSplatInputError(f"camera model {self.model}: parameter {bad[0]} is NaN or inf")
        if self.width < 1 or self.height < 1:
            raise SurfSplatInputError(f"camera model {self.model}: size {self.width}x{self.height} is not positive")

    @property
    def param_names(self) -> tuple[str, ...]:
        return CAMERA_MODELS[MODEL_IDS[self.model]][1]

    @property
    def is_pinhole(self) -> bool:
        """Whether the model projects as a pinhole: a pinhole model, or a perspective model whose
        distortion parameters are all zero (fisheye models never are)."""
        if self.model in PINHOLE_MODELS:
            return True
        if self.model in ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV"):
            first = 3 if self.model.startswith(("SIMPLE_RADIAL", "RADIAL")) else 4
            return all(v == 0 for v in self.params[first:])
        return False

    def to_dict(self) -> dict:
        return {"model": self.model, "width": self.width, "height": self.height, "params": list(self.params)}

    @classmethod
    def from_dict(cls, data: dict, source: str = "lens") -> Lens:
        try:
            return cls(
                str(data["model"]), int(data["width"]), int(data["height"]), tuple(float(v) for v in data["params"])
            )
        except (KeyError, TypeError, ValueError) as err:
            raise SurfSplatInputError(
                f"{source}: a lens needs 'model', 'width', 'height' and 'params' ({type(err).__name__}: {err})"
            ) from None
