"""The simulator: scenes and scene files, reflectors, the receiver chain, echo synthesis,
and ``simulate``, which turns a scene into a recording."""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
