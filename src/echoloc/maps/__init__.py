"""Occupancy maps: located objects accumulated into grids, and the grids exported."""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
