"""Focal length in pixels from a photo's EXIF tags (Pillow reads them; the arithmetic is ours).

Two routes, in order of preference:
- FocalLengthIn35mmFilm (0xA405): the focal length a 36 x 24 mm film frame with the same diagonal
  field of view would need (CIPA DC-008), so f_px = f35 * diagonal_px / 43.27 (the film diagonal).
- FocalLength (0x920A, mm) with FocalPlaneXResolution (0xA20E) / FocalPlaneResolutionUnit (0xA210):
  sensor pixels per unit length along the sensor's width, which is the STORED image's width
  (EXIF 2.3 / CIPA DC-008: the X resolution of the focal plane in the image width direction), at
  the camera's native resolution, PixelXDimension (0xA002) pixels wide. The focal length in stored
  x pixels is rescaled by stored width / PixelXDimension, so a photo downscaled or cropped after
  capture keeps the right focal length; without PixelXDimension the photo is taken at its native size.

The focal length is of the photo as displayed (`surfsplat.data.images.read_image` applies the EXIF
orientation): the 35 mm route uses the diagonal, which no turn changes; the focal-plane route
measures along the stored width, which is the displayed height for orientations 5-8 (a turn of 90
degrees), and with square sensor pixels that is the displayed image's fx as well. HEIC photos are
read through pillow-heif (the `heic` extra), whose EXIF block this reads alike.
"""

from __future__ import annotations

import math
from pathlib import Path

from ..data.images import open_image, orientation_of
from ..geometry.orientation import stored_size

EXIF_IFD = 0x8769
FOCAL_LENGTH = 0x920A
FOCAL_LENGTH_35MM = 0xA405
FOCAL_PLANE_X_RESOLUTION = 0xA20E
FOCAL_PLANE_RESOLUTION_UNIT = 0xA210
PIXEL_X_DIMENSION = 0xA002
PIXEL_Y_DIMENSION = 0xA003
FILM_DIAGONAL_MM = math.hypot(36.0, 24.0)
# FocalPlaneResolutionUnit: 2 = inch, 3 = centimetre (EXIF 2.3), 4 = mm, 5 = micrometre (later revisions).
UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}


def exif_focal(path: str | Path, width: int, height: int) -> tuple[float, str] | None:
    """(focal in pixels of the photo displayed at width x height, which tags gave it), or None without
    usable tags. A file Pillow cannot open raises SurfSplatInputError naming it."""
    with open_image(path, str(path)) as image:
        orientation = orientation_of(image, str(path))
        exif = image.getexif().get_ifd(EXIF_IFD)
    f35 = _number(exif.get(FOCAL_LENGTH_35MM))
    if f35 is not None and f35 > 0:
        return f35 * math.hypot(width, height) / FILM_DIAGONAL_MM, f"EXIF 35 mm equivalent {f35:g} mm"
    f_mm = _number(exif.get(FOCAL_LENGTH))
    resolution = _number(exif.get(FOCAL_PLANE_X_RESOLUTION))
    unit = UNIT_MM.get(int(_number(exif.get(FOCAL_PLANE_RESOLUTION_UNIT)) or 2))
    if f_mm is None or f_mm <= 0 or resolution is None or resolution <= 0 or unit is None:
        return None
    stored_width, _ = stored_size(orientation, width, height)
    native_width = _number(exif.get(PIXEL_X_DIMENSION))
    rescale = stored_width / native_width if native_width and native_width > 0 else 1.0
    focal = f_mm * resolution / unit * rescale
    return focal, f"EXIF focal length {f_mm:g} mm at {resolution:g} px per {unit:g} mm"


def _number(value: object) -> float | None:
    """EXIF rationals, ints and floats -> float; anything else (missing, malformed) -> None."""
    try:
        number = float(value)  # IFDRational, int and float all convert
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return number if math.isfinite(number) else None
