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


@pytest.mark.parametrize("name", ["seed_candidates", "refine"])
def test_the_seed_and_refinement_kernels_start_with_the_geometry_s_fields(name: str) -> None:
    parameters = _parameters(getattr(locate_kernels, name))
    assert parameters[: len(KernelGeometry._fields)] == list(KernelGeometry._fields)


_ASSOCIATION = ["geometry", "paths", "sigmas", "amplitudes", "offset", "tail", "node_limit", "max_rows"]


def test_candidates_and_associate_take_the_bundles_whole_and_read_every_field() -> None:
    """``candidates`` and ``associate`` take the geometry and the tail whole; between them
    they read every field (candidates for the seeds and the refinement, associate for the
    choice), and associate hands both bundles on to candidates as they are."""
    assert _parameters(locate_kernels.candidates) == _ASSOCIATION
    assert _parameters(locate_kernels.associate) == [*_ASSOCIATION, "origin"]
    for name, fields in (("geometry", KernelGeometry._fields), ("tail", AssociationTail._fields)):
        read = _fields_read(locate_kernels.candidates, name) | _fields_read(locate_kernels.associate, name)
        assert read == set(fields), name
    calls = [
        node
        for node in ast.walk(_kernel_tree(locate_kernels.associate))
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "candidates"
    ]
    assert len(calls) == 1
    assert [ast.unparse(a) for a in calls[0].args] == _ASSOCIATION


def test_associate_frame_hands_every_field_to_associate_s_parameter_of_its_name() -> None:
    """associate_frame takes the locate bundle whole and the frame's echoes; it hands the
    geometry, the tail and the bundle's limits to :func:`associate`, each in the place of the
    parameter of its own name, and reads the rest (speed, prior variance, carrier)."""
    kernel = locate_kernels.associate_frame
    assert _parameters(kernel) == ["arguments", "tof", "snr_db", "amplitudes", "offset"]
    assert _fields_read(kernel, "arguments") == set(LocateKernelArguments._fields)
    calls = [
        node
        for node in ast.walk(_kernel_tree(kernel))
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "associate"
    ]
    assert len(calls) == 1
    parameters = _parameters(locate_kernels.associate)
    assert len(calls[0].args) == len(parameters)
    assert not calls[0].keywords
    handed: set[str] = set()
    for parameter, value in zip(parameters, calls[0].args, strict=True):
        if isinstance(value, ast.Attribute) and isinstance(value.value, ast.Name):
            assert value.value.id == "arguments", ast.unparse(value)
            assert value.attr == parameter, ast.unparse(value)
            handed.add(parameter)
        else:
            assert ast.unparse(value) == parameter
    assert handed == {"geometry", "tail", "node_limit", "max_rows", "origin"}
