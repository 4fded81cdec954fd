"""The spacing study as a library call (``echoloc design`` prints it): the report's
figures 4.12 and 4.13, the symmetry of its cross array, and what it refuses."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from echoloc.cli import commands
from echoloc.errors import EchoLocError
from echoloc.localise.design import design_record, design_study
from echoloc.localise.uncertainty import recommended_spacing


def test_the_command_prints_the_library_s_study() -> None:
    """`echoloc design --json` is :func:`design_record` of :func:`design_study`, nothing else."""
    result = CliRunner().invoke(
        commands.cli, ["design", "--range-m", "0.8", "--path-error-m", "0.003", "--json"]
    )
    assert result.exit_code == 0, result.output
    study = design_study(0.003, range_m=0.8)
    assert json.loads(result.output) == json.loads(json.dumps(design_record(study)))


def test_the_default_is_the_report_s_study() -> None:
    """l = 1 m and Δl = 5 mm (figure 4.13): the recommendation is recommended_spacing's, the
    uncertainty area (figure 4.12) is mirror-symmetric about the boresight."""
    study = design_study(0.005)
    assert study.path_m == 1.0
    assert study.recommendation == recommended_spacing(0.005, path_m=1.0)
    assert 0.2 <= study.spacing_m <= 0.3
    corners = study.area.corners_m
    assert corners[0, 0] == pytest.approx(-corners[2, 0], abs=1e-12)
    assert corners[0, 1] == pytest.approx(corners[2, 1], abs=1e-12)


def test_the_cross_array_maps_the_same_in_its_two_vertical_planes() -> None:
    """The report's cross is symmetric under x <-> y: its GDOP over the xz plane is its
    GDOP over the yz plane."""
    xz = design_study(0.005, plane="xz").gdop_map.errors.gdop
    yz = design_study(0.005, plane="yz").gdop_map.errors.gdop
    np.testing.assert_allclose(xz, yz, rtol=1e-9, equal_nan=True)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"path_m": 1.0, "range_m": 1.0}, "not both"),
        ({"path_m": 0.4, "spacing_m": 0.5}, "must be below the path"),
    ],
)
def test_what_it_refuses(kwargs: dict[str, float], match: str) -> None:
    with pytest.raises(EchoLocError, match=match):
        design_study(0.005, **kwargs)  # type: ignore[arg-type]
