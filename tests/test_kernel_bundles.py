"""The compiled kernels' argument bundles: named tuples whose fields are the kernels' parameters.

Python passes a kernel its arguments as named tuples (``*bundle`` where the kernel takes
them one by one). A field added, dropped or moved in a bundle, or a parameter in a kernel,
would shift every argument after it without an error: these tests hold the two to each
other by name.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

import pytest

from echoloc.localise import _locate_kernels as locate_kernels
from echoloc.localise.locate import AssociationTail, KernelGeometry, LocateKernelArguments
from echoloc.tof import _echoes_kernels as echo_kernels
from echoloc.tof.echoes import EchoKernelArguments, FinishingConstants


def _parameters(kernel: Callable[..., Any]) -> list[str]:
    """A kernel's parameter names (a compiled kernel's Python function's)."""
    return list(inspect.signature(getattr(kernel, "py_func", kernel)).parameters)


def test_the_echo_bundle_is_correlate_and_fit_s_parameters() -> None:
    assert _parameters(echo_kernels.correlate_and_fit) == list(EchoKernelArguments._fields)


def test_the_finishing_constants_are_finish_channels_parameters() -> None:
    parameters = _parameters(echo_kernels.finish_channels)
    start = parameters.index("lag_rate_hz")
    assert parameters[start : start + len(FinishingConstants._fields)] == list(FinishingConstants._fields)


@pytest.mark.parametrize("name", ["seed_candidates", "refine", "candidates", "associate", "associate_frame"])
def test_every_association_kernel_starts_with_the_geometry(name: str) -> None:
    parameters = _parameters(getattr(locate_kernels, name))
    assert parameters[: len(KernelGeometry._fields)] == list(KernelGeometry._fields)


@pytest.mark.parametrize("name", ["candidates", "associate", "associate_frame"])
def test_the_association_tail_follows_the_echo_offsets(name: str) -> None:
    parameters = _parameters(getattr(locate_kernels, name))
    start = parameters.index("offset") + 1
    assert parameters[start : start + len(AssociationTail._fields)] == list(AssociationTail._fields)


def test_associate_frame_takes_the_locate_bundle_in_its_order() -> None:
    """FrameLocator passes ``*geometry, tof, speed, snr_db, prior_variance, omega, amplitudes,
    offset, *tail, node_limit, max_rows, origin``: the bundle's scalars land on these names."""
    parameters = _parameters(locate_kernels.associate_frame)
    n_geometry, n_tail = len(KernelGeometry._fields), len(AssociationTail._fields)
    echoes = parameters[n_geometry : parameters.index("offset") + 1]
    assert echoes == ["tof", "speed", "snr_db", "prior_variance", "omega", "amplitudes", "offset"]
    after_tail = parameters[parameters.index("offset") + 1 + n_tail :]
    assert after_tail == ["node_limit", "max_rows", "origin"]
    assert LocateKernelArguments._fields == (
        "geometry",
        "speed_of_sound_m_s",
        "prior_variance_m2",
        "omega_rad_s",
        "tail",
        "node_limit",
        "max_rows",
        "origin",
    )
