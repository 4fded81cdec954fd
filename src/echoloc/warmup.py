"""Compiling the numba kernels ahead, and telling whether they still need compiling.

The kernels (``tof/_echoes_kernels.py``, ``localise/_locate_kernels.py``,
``maps/_mapping_kernels.py``, ``_chain_kernels.py``) compile on their first call and are
cached on disk beside their module (or in ``NUMBA_CACHE_DIR``). That first compilation
takes minutes on a small machine; later runs load the cache in about a second.
:func:`warm_up` makes the calls that compile them, one stage at a time, so that a user
can do it once with progress (``echoloc warmup``) instead of meeting it, silent, inside
the first command. :func:`kernels_cold` tells from the on-disk cache whether that first
compilation is still ahead.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable, Iterator
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
    them); False when they have one, or when numba's cache cannot be inspected."""
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
    """One stage of :func:`warm_up`: its name and the calls that compile its kernels."""

    name: str
    run: Callable[[], Any]


def _matched_chain(workers: int = 1) -> Any:
    from echoloc.pipeline import prepare, run
    from echoloc.sim.scene import default_scene
    from echoloc.sim.simulation import simulate
    from echoloc.tof.echoes import EchoOptions

    recording = simulate(default_scene(), 4)
    return list(run(prepare(recording, echo_options=EchoOptions(workers=workers))))


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


def warm_up_steps(workers: int = 2) -> tuple[WarmUpStep, ...]:
    """The stages :func:`warm_up` compiles, in order (``workers``: also the threaded
    matched filter, as ``--workers N`` runs it, when above 1)."""
    steps = [
        WarmUpStep("matched filter and association", _matched_chain),
        WarmUpStep("overlapping echoes (CLEAN, shared echoes)", _crowded_chain),
        WarmUpStep("envelope chips (CH101 preset)", _envelope_chain),
        WarmUpStep("occupancy maps", _occupancy_map),
    ]
    if workers > 1:
        steps.insert(1, WarmUpStep(f"matched filter on {workers} threads", lambda: _matched_chain(workers)))
    return tuple(steps)


def warm_up(workers: int = 2) -> Iterator[str]:
    """Compile (or load) every stage's kernels; yields each step's name as it starts."""
    for step in warm_up_steps(workers):
        yield step.name
        step.run()
