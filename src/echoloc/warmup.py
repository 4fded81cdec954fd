"""Compiling the numba kernels ahead, and telling whether they still need compiling.

The kernels (``tof/_echoes_kernels.py``, ``localise/_locate_kernels.py``,
``maps/_mapping_kernels.py``, ``_chain_kernels.py``) compile on their first call and are
cached on disk beside their module (or in ``NUMBA_CACHE_DIR``). That first compilation
takes minutes on a small machine; later runs load the cache in about a second.
The steps of :func:`warm_up_steps` make the calls that compile them, one stage at a
time, so that a user can do it once with progress (``echoloc warmup``) instead of
meeting it, silent, inside the first command. :func:`kernels_cold` tells from the
on-disk cache whether that first compilation is still ahead.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from typing import Any

import numpy as np

# The entry kernels every chain calls: when their cache is missing or stale, the next
# command compiles (module, function).
_ENTRY_KERNELS = (
    ("echoloc.tof._echoes_kernels", "batch_echoes"),
    ("echoloc.localise._locate_kernels", "seed_candidates"),
    ("echoloc._chain_kernels", "echoes_and_objects"),
)


def kernels_cold() -> bool:
    """True when the entry kernels have no valid on-disk cache (the next chain compiles
    them); False when they have one, when numba is not installed (nothing compiles), or
    when numba's cache cannot be inspected."""
    from echoloc._jit import HAVE_NUMBA

    if not HAVE_NUMBA:
        return False
    for module_name, function_name in _ENTRY_KERNELS:
        dispatcher = getattr(importlib.import_module(module_name), function_name)
        try:
            # numba's FunctionCache: its index is empty when missing, or stale against the
            # source's timestamp and size (numba then recompiles).
            index = dispatcher._cache._cache_file._load_index()
        except Exception:  # a numba without this layout: no claim either way
            return False
        if not index:
            return True
    return False


@dataclasses.dataclass(frozen=True)
class WarmUpStep:
    """One stage of :func:`warm_up_steps`: its name and the calls that compile its kernels."""

    name: str
    run: Callable[[], Any]


def _crowded_chain() -> Any:
    """Reflectors close in range, so that echoes overlap: CLEAN, pair splitting, shared echoes."""
    from echoloc.pipeline import prepare, run
    from echoloc.sim.scene import default_scene
    from echoloc.sim.scenefile import scene_from_dict
    from echoloc.sim.simulation import simulate

    base = default_scene()
    scene = scene_from_dict(
        {
            "seed": 3,
            "array": {
                "transmitters_m": base.array.transmitters_m.tolist(),
                "receivers_m": base.array.receivers_m.tolist(),
            },
            "acquisition": {"sample_rate_hz": 200e3, "n_samples": 2400},
            "random_reflectors": {
                "count": [4, 6],
                "x_m": [-0.3, 0.3],
                "y_m": [-0.3, 0.3],
                "z_m": [0.5, 0.6],
            },
        },
        source="<warm-up scene>",
    )
    return list(run(prepare(simulate(scene, 6))))


def _envelope_chain() -> Any:
    from echoloc.pipeline import prepare, run
    from echoloc.sim.scenefile import load_scene
    from echoloc.sim.simulation import simulate

    return list(run(prepare(simulate(load_scene("ch101"), 4), estimator="auto")))


def _occupancy_map() -> Any:
    from echoloc.maps.mapping import GridSpec, build_map
    from echoloc.pipeline import prepare, run
    from echoloc.sim.scene import default_scene
    from echoloc.sim.simulation import simulate

    recording = simulate(default_scene(), 2)
    spec = GridSpec(np.array([-0.5, -0.5, 0.0]), 0.05, (20, 20, 24))
    return build_map(recording, run(prepare(recording)), spec)


def _reflector_classes() -> Any:
    """The corridor with two transmitters located with classes: every hypothesis's fit."""
    import dataclasses

    from echoloc.pipeline import prepare, run
    from echoloc.sim.scenefile import load_scene
    from echoloc.sim.simulation import simulate

    chain = prepare(simulate(load_scene("rooms/corridor"), 3))
    options = dataclasses.replace(chain.locate_options, reflector_classes=True)
    return list(run(dataclasses.replace(chain, locate_options=options)))


def warm_up_steps(workers: int = 2) -> tuple[WarmUpStep, ...]:
    """The stages ``echoloc warmup`` compiles, in order (``workers``: also the threaded
    matched filter, as ``--workers N`` runs it, when above 1)."""
    from echoloc.realtime.stream import warm_kernels  # a stream's own warm-up: the same kernels

    steps = [
        WarmUpStep("matched filter and association", lambda: warm_kernels("matched", 1)),
        WarmUpStep("overlapping echoes (CLEAN, shared echoes)", _crowded_chain),
        WarmUpStep("envelope chips (CH101 preset)", _envelope_chain),
        WarmUpStep("occupancy maps", _occupancy_map),
        WarmUpStep("reflector classes (planes, corners, edges)", _reflector_classes),
    ]
    if workers > 1:
        threaded = WarmUpStep(
            f"matched filter on {workers} threads", lambda: warm_kernels("matched", workers)
        )
        steps.insert(1, threaded)
    return tuple(steps)
