"""Emitted codes and the sampled pulses built from them.

A code is a sequence of ±1 bits. :func:`modulate` puts it on a carrier with N
carrier cycles per bit: bit +1 sends the carrier, bit -1 the inverted carrier
(binary phase-shift keying), as in the report's ch. 3.4.

Barker sequences (report ch. 3.4; R. H. Barker, "Group synchronizing of binary
digital systems", 1953): the aperiodic autocorrelation of every one has sidelobes
of magnitude at most 1 against a peak equal to the length.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from echoloc.errors import WaveformError

BARKER_CODES: dict[int, tuple[tuple[int, ...], ...]] = {
    2: ((1, 1), (-1, 1)),
    3: ((1, 1, -1),),
    4: ((1, 1, -1, 1), (1, 1, 1, -1)),
    5: ((1, 1, 1, -1, 1),),
    7: ((1, 1, 1, -1, -1, 1, -1),),
    11: ((1, 1, 1, -1, -1, -1, 1, -1, -1, 1, -1),),
    13: ((1, 1, 1, 1, 1, -1, -1, 1, 1, -1, 1, -1, 1),),
}
"""Every known Barker sequence, by length; the first variant is the default."""

Carrier = Literal["sine", "square"]


@dataclass(frozen=True, eq=False)
class Waveform:
    """A sampled pulse as an ideal point reflector returns it.

    ``samples[0]`` is the instant emission starts. ``carrier_hz`` is the centre
    frequency; ``chip_s`` the duration of one code bit (0 when not a code).
    """

    samples: NDArray[np.float64]
    sample_rate_hz: float
    carrier_hz: float
    name: str
    chip_s: float = 0.0

    @property
    def duration_s(self) -> float:
        return len(self.samples) / self.sample_rate_hz


def barker(length: int, variant: int = 0) -> NDArray[np.int8]:
    """The Barker sequence of ``length`` (2, 3, 4, 5, 7, 11 or 13) as ±1 values."""
    if length not in BARKER_CODES:
        valid = ", ".join(str(n) for n in BARKER_CODES)
        raise WaveformError(f"no Barker code of length {length}; they exist for lengths {valid}")
    variants = BARKER_CODES[length]
    if not 0 <= variant < len(variants):
        raise WaveformError(f"Barker {length} has {len(variants)} variant(s), not index {variant}")
    return np.array(variants[variant], dtype=np.int8)


def aperiodic_autocorrelation(code: ArrayLike) -> NDArray[np.float64]:
    """Aperiodic autocorrelation ``r[k] = sum_n c[n] c[n+k]`` for lags -(N-1)..N-1."""
    c = np.asarray(code, dtype=float)
    return np.asarray(np.correlate(c, c, mode="full"))


def modulate(
    code: ArrayLike,
    *,
    carrier_hz: float,
    cycles_per_bit: int,
    sample_rate_hz: float,
    carrier: Carrier = "sine",
    name: str = "code",
) -> Waveform:
    """Put a ±1 code on a carrier: bit b sends ``b * carrier(t)`` for N cycles.

    The carrier starts at phase 0 at t = 0 and runs continuously through the bits,
    so a sign change of the code is a phase reversal of 180°. The ``square``
    carrier is +1 for the first half of each cycle and -1 for the second.
    """
    bits = np.asarray(code, dtype=float)
    if bits.ndim != 1 or bits.size == 0 or not np.all(np.abs(bits) == 1):
        raise WaveformError("a code must be a non-empty sequence of +1 and -1")
    if not (carrier_hz > 0 and sample_rate_hz > 0):
        raise WaveformError(f"carrier ({carrier_hz} Hz) and sample rate ({sample_rate_hz} Hz) must be > 0")
    if carrier_hz >= sample_rate_hz / 2:
        raise WaveformError(
            f"carrier {carrier_hz:g} Hz is not below the Nyquist frequency {sample_rate_hz / 2:g} Hz"
        )
    if int(cycles_per_bit) != cycles_per_bit or cycles_per_bit < 1:
        raise WaveformError(f"cycles_per_bit must be a positive whole number, got {cycles_per_bit}")
    chip_s = cycles_per_bit / carrier_hz
    n_samples = round(bits.size * chip_s * sample_rate_hz)
    t = np.arange(n_samples) / sample_rate_hz
    # Cycles elapsed at each sample, rounded to guard samples that fall on an edge.
    cycles = np.round(t * carrier_hz, 9)
    if carrier == "sine":
        wave = np.sin(2 * np.pi * cycles)
    elif carrier == "square":
        wave = np.where(np.floor(2 * cycles) % 2 == 0, 1.0, -1.0)
    else:
        raise WaveformError(f"carrier must be 'sine' or 'square', got {carrier!r}")
    bit_index = np.minimum((cycles // cycles_per_bit).astype(int), bits.size - 1)
    return Waveform(
        samples=wave * bits[bit_index],
        sample_rate_hz=float(sample_rate_hz),
        carrier_hz=float(carrier_hz),
        name=name,
        chip_s=chip_s,
    )


def barker_waveform(
    length: int = 13,
    *,
    carrier_hz: float = 50e3,
    cycles_per_bit: int = 4,
    sample_rate_hz: float = 200e3,
    carrier: Carrier = "sine",
    variant: int = 0,
) -> Waveform:
    """Barker code of ``length`` on a carrier; defaults are the report's Barker-13 × 4 at 50 kHz."""
    return modulate(
        barker(length, variant),
        carrier_hz=carrier_hz,
        cycles_per_bit=cycles_per_bit,
        sample_rate_hz=sample_rate_hz,
        carrier=carrier,
        name=f"barker{length}",
    )
