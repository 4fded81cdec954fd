"""Types of echoloc.sim's public names; lazy_loader reads its imports to load each on first use."""

from .scene import Array, Scene, default_scene
from .scenefile import load_scene, preset_names, preset_path
from .simulation import recording_header, simulate, simulate_to_file

__all__ = [
    "Array",
    "Scene",
    "default_scene",
    "load_scene",
    "preset_names",
    "preset_path",
    "recording_header",
    "simulate",
    "simulate_to_file",
]
