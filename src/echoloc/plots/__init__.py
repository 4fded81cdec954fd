"""Pictures (matplotlib): a frame, the physics (beams, spectra), images, maps, design studies."""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
