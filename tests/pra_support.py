"""What the tests against pyroomacoustics (pra) share: pra without its RIR high-pass filter,
and the fixed delay its fractional-delay filter adds to every arrival."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

pra = pytest.importorskip("pyroomacoustics")


@pytest.fixture(autouse=True)
def _pra_without_highpass() -> Iterator[None]:
    """Switch pra's RIR high-pass filter off for a test, restoring the global setting after."""
    before = pra.constants.get("rir_hpf_enable")
    pra.constants.set("rir_hpf_enable", False)
    yield
    pra.constants.set("rir_hpf_enable", before)


def pra_offset_samples() -> int:
    """The delay pra adds to every arrival: half its fractional-delay filter (ism.py, fdl // 2)."""
    return int(pra.constants.get("frac_delay_length")) // 2
