"""Types of echoloc.plots's public names; lazy_loader reads its imports to load each on first use."""

from .design import plot_error_map, plot_spacing_study, plot_uncertainty_area
from .frame import plot_frame
from .imaging import save_image_png
from .maps import plot_grid
from .physics import plot_air, plot_beam, plot_waveform

__all__ = [
    "plot_air",
    "plot_beam",
    "plot_error_map",
    "plot_frame",
    "plot_grid",
    "plot_spacing_study",
    "plot_uncertainty_area",
    "plot_waveform",
    "save_image_png",
]
