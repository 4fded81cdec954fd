"""The optional parts of echoloc and what they need installed.

The core (recordings, the simulator, time of flight, localisation, maps, the wire
protocol, MCAP and PLY exports) installs with numpy, scipy, h5py, mcap and the command
line's click and rich. The rest are extras of the package:

- ``fast``: the kernels compiled (numba, rocket-fft). Without it they run as plain Python,
  the same answers 7-50 times slower a frame, and echoloc says so once
  (:mod:`echoloc._jit`);
- ``plot``: every picture (``--plot``, ``image``, a ``map`` as PNG, ``design -o``): matplotlib;
- ``live``: the live view of ``stream --view`` (Foxglove WebSocket): foxglove-sdk;
- ``octomap``: maps written as OctoMap (``.bt``, ``.ot``): pyoctomap;
- ``serial``: capture from a board on a serial or USB-CDC port (``--source serial:PORT``):
  pyserial;
- ``soundcard``: capture from a sound card (``--source soundcard``): sounddevice, which needs
  the PortAudio library (on Linux the system package ``libportaudio2``);
- ``cluster``: ``echoloc batch`` and ``echoloc sweep`` on a Dask cluster: dask.distributed.

``pip install 'echoloc[all]'`` installs all seven.
"""

from __future__ import annotations

from echoloc.errors import EchoLocError

EXTRAS = {
    "fast": "numba",
    "plot": "matplotlib",
    "live": "foxglove-sdk",
    "octomap": "pyoctomap",
    "serial": "pyserial",
    "soundcard": "sounddevice",
    "cluster": "dask[distributed]",
}
"""Each extra and the distribution it installs."""


def missing_extra(extra: str, purpose: str) -> EchoLocError:
    """The error for ``purpose`` (what the user asked for) when ``extra`` is not installed."""
    return EchoLocError(
        f"{purpose} needs {EXTRAS[extra]}, which is not installed: pip install 'echoloc[{extra}]'"
    )
