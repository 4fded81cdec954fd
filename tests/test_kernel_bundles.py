"""The compiled kernels' argument bundles: named tuples whose fields are the kernels' parameters.

Python passes a kernel its arguments as named tuples: ``*bundle`` where the kernel takes them
one by one (a field added, dropped or moved, or a parameter, would shift every argument after
it without an error), or the bundle whole where the kernel reads its fields by name (a field
left unread, or handed on to the wrong parameter, would go unnoticed). These tests hold the
two to each other by name.
"""

from __future__ import annotations

import ast
import inspect
import textwrap
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


def _kernel_tree(kernel: Callable[..., Any]) -> ast.FunctionDef:
    source = textwrap.dedent(inspect.getsource(getattr(kernel, "py_func", kernel)))
    tree = ast.parse(source).body[0]
    assert isinstance(tree, ast.FunctionDef)
    return tree


def _fields_read(kernel: Callable[..., Any], name: str) -> set[str]:
    """The attributes a kernel reads of its variable ``name``."""
    return {
        node.attr
        for node in ast.walk(_kernel_tree(kernel))
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == name
    }


def test_correlate_and_fit_takes_the_echo_bundle_and_reads_every_field() -> None:
    assert _parameters(echo_kernels.correlate_and_fit) == ["arguments"]
    assert _fields_read(echo_kernels.correlate_and_fit, "arguments") == set(EchoKernelArguments._fields)


def test_the_finishing_constants_are_finish_channels_parameters() -> None:
    parameters = _parameters(echo_kernels.finish_channels)
    start = parameters.index("lag_rate_hz")
    assert parameters[start : start + len(FinishingConstants._fields)] == list(FinishingConstants._fields)


@pytest.mark.parametrize("name", ["seed_candidates", "refine", "candidates", "associate"])
def test_every_association_kernel_starts_with_the_geometry(name: str) -> None:
    parameters = _parameters(getattr(locate_kernels, name))
    assert parameters[: len(KernelGeometry._fields)] == list(KernelGeometry._fields)


@pytest.mark.parametrize("name", ["candidates", "associate"])
def test_the_association_tail_follows_the_echo_offsets(name: str) -> None:
    parameters = _parameters(getattr(locate_kernels, name))
    start = parameters.index("offset") + 1
    assert parameters[start : start + len(AssociationTail._fields)] == list(AssociationTail._fields)


def test_associate_frame_hands_every_field_to_associate_s_parameter_of_its_name() -> None:
    """associate_frame takes the locate bundle whole and the frame's echoes; it hands the
    geometry's, the tail's and the bundle's limits to :func:`associate` by keyword, each field
    to the parameter of its own name, and reads the rest (speed, prior variance, carrier)."""
    kernel = locate_kernels.associate_frame
    assert _parameters(kernel) == ["arguments", "tof", "snr_db", "amplitudes", "offset"]
    assert _fields_read(kernel, "arguments") == set(LocateKernelArguments._fields)
    calls = [
        node
        for node in ast.walk(_kernel_tree(kernel))
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "associate"
    ]
    assert len(calls) == 1
    handed: dict[str, set[str]] = {"geometry": set(), "tail": set(), "arguments": set()}
    for keyword in calls[0].keywords:
        value = keyword.value
        if isinstance(value, ast.Attribute) and isinstance(value.value, ast.Name):
            assert keyword.arg == value.attr, ast.unparse(keyword)
            handed[value.value.id].add(value.attr)
    assert handed["geometry"] == set(KernelGeometry._fields)
    assert handed["tail"] == set(AssociationTail._fields)
    assert handed["arguments"] == {"node_limit", "max_rows", "origin"}
    assert {k.arg for k in calls[0].keywords} == set(_parameters(locate_kernels.associate))
