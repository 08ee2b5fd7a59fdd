"""What people look at: PLY files (and, with later modules, images, videos and meshes)."""

from .ply import load_ply, save_ply

__all__ = ["load_ply", "save_ply"]
