"""Pictures (matplotlib): a frame, the physics (beams, spectra), images, maps, design studies.

matplotlib is the ``plot`` extra (``pip install 'echoloc[plot]'``); without it, importing
any of these says so in one line."""

import lazy_loader

from echoloc.extras import missing_extra

try:
    import matplotlib
except ImportError:
    raise missing_extra("plot", "drawing pictures") from None

del matplotlib  # imported to find it; each module imports what it draws with

__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
