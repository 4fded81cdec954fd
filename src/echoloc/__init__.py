"""echoloc: airborne ultrasonic echolocation for robots.

The data flow is the architecture: ``scene -> simulate -> Recording -> echoes ->
locate -> objects``, one module per stage (see docs/ARCHITECTURE.md).

Its public names (``__all__``) are loaded on first use (PEP 562, through
``lazy_loader.attach_stub``, which reads them from ``__init__.pyi``, the typed list): ``import
echoloc`` or ``from echoloc.realtime.protocol import encode_frame`` does not import numba, scipy and
every stage (about a second), and ``echoloc.X`` is still ``X`` of its module. Set
``EAGER_IMPORT=1`` to load everything at once.
"""

import lazy_loader

__version__ = "0.1.0"

__getattr__, _, _lazy_names = lazy_loader.attach_stub(__name__, __file__)
__all__ = [*_lazy_names, "__version__"]


def __dir__() -> list[str]:
    return list(__all__)
