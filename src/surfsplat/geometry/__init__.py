"""Conventions: cameras, rotations, spherical harmonics."""

from .cameras import Cameras, rigid_inverse
from .rotations import matrix_to_quat, quat_to_matrix
from .sh import eval_sh, num_sh_bases, sh_to_color

__all__ = ["Cameras", "rigid_inverse", "matrix_to_quat", "quat_to_matrix", "eval_sh", "num_sh_bases", "sh_to_color"]
