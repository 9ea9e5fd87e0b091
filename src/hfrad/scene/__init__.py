"""Scenes: meshes, materials, patches, built-in scenes and Z-order."""

from .builtin import BUILTIN_SCENES, builtin_scene
from .patches import drop_degenerate, subdivide
from .scene import Material, Scene
from .zorder import morton_codes, zorder_permutation

__all__ = ["BUILTIN_SCENES", "Material", "Scene", "builtin_scene", "drop_degenerate",
           "morton_codes", "subdivide", "zorder_permutation"]
