"""Live data: the wire protocol, TCP/UDP transport, the stream that processes frames as
they arrive, and the live view."""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
