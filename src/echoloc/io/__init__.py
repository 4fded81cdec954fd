"""Files in and out: HDF5/NPZ recordings, importers of other data sets, JSON Lines, and
MCAP/PLY exports."""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
