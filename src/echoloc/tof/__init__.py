"""Time of flight: from a frame of received samples to echoes (arrival times, amplitudes,
uncertainty) through matched filters, envelopes, thresholds and fits; channel conditioning
and health; templates."""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
