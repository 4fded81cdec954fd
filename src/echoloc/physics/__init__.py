"""The physics the rest stands on: air (speed of sound, absorption), transducers (beams,
responses), the transmitted waveforms and codes, and the Cramér-Rao bounds on timing."""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
