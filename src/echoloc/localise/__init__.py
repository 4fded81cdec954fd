"""From echoes to positions: association across receivers and ellipsoid intersection,
back-projection, calibration, evaluation against the truth, position uncertainty."""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
