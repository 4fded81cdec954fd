"""Types of echoloc's stable public API; lazy_loader reads its imports to load each name on first use.

The names here are the stable API. The subpackages hold the rest, each with its own list."""

from . import io, localise, maps, physics, plots, realtime, sim, tof
from .errors import EchoLocError
from .io.recording import Recording, read_recording, write_recording
from .localise.evaluation import Evaluation, evaluate
from .localise.locate import FrameObjects, LocatedObject, LocateOptions
from .pipeline import Chain, prepare, run
from .sim.scene import Array, Scene, default_scene
from .sim.scenefile import load_scene
from .sim.simulation import simulate
from .tof.echoes import ChannelEchoes, EchoOptions, FrameEchoes

__version__: str

__all__ = [
    "Array",
    "Chain",
    "ChannelEchoes",
    "EchoLocError",
    "EchoOptions",
    "Evaluation",
    "FrameEchoes",
    "FrameObjects",
    "LocateOptions",
    "LocatedObject",
    "Recording",
    "Scene",
    "__version__",
    "default_scene",
    "evaluate",
    "io",
    "load_scene",
    "localise",
    "maps",
    "physics",
    "plots",
    "prepare",
    "read_recording",
    "realtime",
    "run",
    "sim",
    "simulate",
    "tof",
    "write_recording",
]
