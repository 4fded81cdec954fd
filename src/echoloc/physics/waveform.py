"""Emitted codes, the sampled pulses built from them, and their correlation metrics.

A code is a sequence of ±1 bits. :func:`modulate` puts it on a carrier with N
carrier cycles per bit: bit +1 sends the carrier, bit -1 the inverted carrier
(binary phase-shift keying), as in the report's ch. 3.4.

Barker sequences (report ch. 3.4; R. H. Barker, "Group synchronizing of binary
digital systems", 1953): the aperiodic autocorrelation of every one has sidelobes
of magnitude at most 1 against a peak equal to the length.

The other codes the report names as alternatives (ch. 3.4.3.4) are here too: Golay
complementary pairs (:func:`golay_pair`), maximal-length sequences (:func:`mls`) and
the small Kasami set (:func:`kasami_set`), whose low cross-correlation lets several
transmitters fire at once. Besides codes: linear and hyperbolic FM chirps
(:func:`chirp_waveform`) and the plain tone burst of Polaroid-style ranging modules
(:func:`tone_burst`). :func:`waveform_by_name` builds any of them from a short name
such as ``"barker13"``, ``"golay16a"``, ``"mls7"``, ``"kasami6:2"`` or ``"lfm"``.

Metrics: :func:`code_metrics` for a bare ±1 code (peak sidelobe, merit factor),
:func:`waveform_metrics` for a sampled pulse, optionally after a transducer's
impulse response (peak-to-sidelobe ratio and integrated sidelobe level of the
matched-filter envelope, -3 dB main-lobe width and the range resolution it implies,
-3 dB bandwidth), and :func:`peak_cross_correlation` between two codes or pulses.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import scipy.fft
import scipy.signal
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


MAX_WAVEFORM_SAMPLES = 1 << 20
"""The most samples a pulse may have (5 s at 200 kHz; real pulses last a few ms): checked
before the pulse is built, since a large cycles_per_bit or duration would otherwise
allocate gigabytes before anything refused it."""


def _pulse_samples(count: float, what: str) -> int:
    """``count`` rounded, refused beyond :data:`MAX_WAVEFORM_SAMPLES` before anything is allocated."""
    if not (math.isfinite(count) and count <= MAX_WAVEFORM_SAMPLES):
        raise WaveformError(
            f"{what} would have {count:.3g} samples, more than the {MAX_WAVEFORM_SAMPLES} a pulse may have "
            "(fewer cycles_per_bit, a shorter duration, or a lower sample rate)"
        )
    return round(count)


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
    n_samples = _pulse_samples(bits.size * chip_s * sample_rate_hz, "the coded pulse")
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


# --------------------------------------------------------------------------- codes


def _whole(value: int, what: str) -> int:
    """``value`` as an int, or WaveformError naming ``what`` when it is not a whole number."""
    try:
        as_int = int(value)
    except (TypeError, ValueError, OverflowError):
        raise WaveformError(f"{what} must be a whole number, got {value!r}") from None
    if isinstance(value, bool) or as_int != value:
        raise WaveformError(f"{what} must be a whole number, got {value!r}")
    return as_int


GOLAY_MAX_LENGTH = 1 << 20
"""Longest pair :func:`golay_pair` builds: a guard against runaway memory, not a limit of the construction."""


def golay_pair(length: int) -> tuple[NDArray[np.int8], NDArray[np.int8]]:
    """A Golay complementary pair ``(a, b)`` of ±1 sequences of ``length`` (a power of two, 2..2**20).

    Built by the standard recursion from ``a = b = [+1]``: ``a' = a | b`` and
    ``b' = a | -b`` (``|`` is concatenation), which doubles the length and keeps the
    pair complementary (M. J. E. Golay, "Complementary series", IRE Trans. Inf.
    Theory IT-7(2), 82-87, 1961). Complementary means that the aperiodic
    autocorrelations add to a delta: ``r_a[k] + r_b[k] = 2 N`` at ``k = 0`` and 0 at
    every other lag, so transmitting both (one after the other, or from two
    channels) and adding the matched-filter outputs leaves no sidelobes at all.

    Parameters
    ----------
    length
        Number of bits N, a power of two from 2 to 2**20.

    Returns
    -------
    a, b
        The pair as int8 arrays of +1 and -1; ``golay_pair(2)`` is ``([1, 1], [1, -1])``.
    """
    n = _whole(length, "Golay length")
    if n < 2 or n > GOLAY_MAX_LENGTH or n & (n - 1):
        raise WaveformError(
            f"Golay pairs here have a power-of-two length 2..{GOLAY_MAX_LENGTH}, got {length}"
        )
    a = np.ones(1, dtype=np.int8)
    b = np.ones(1, dtype=np.int8)
    while a.size < n:
        a, b = np.concatenate((a, b)), np.concatenate((a, -b))
    return a, b


MLS_TAPS: dict[int, tuple[int, ...]] = {
    2: (2, 1),
    3: (3, 2),
    4: (4, 3),
    5: (5, 3),
    6: (6, 5),
    7: (7, 6),
    8: (8, 6, 5, 4),
    9: (9, 5),
    10: (10, 7),
    11: (11, 9),
    12: (12, 6, 4, 1),
    13: (13, 4, 3, 1),
    14: (14, 5, 3, 1),
    15: (15, 14),
    16: (16, 15, 13, 4),
}
"""Feedback taps of a maximal-length LFSR for each order m = 2..16.

Taps ``(m, t2, ...)`` stand for the recurrence ``s[n] = s[n-m] ^ s[n-t2] ^ ...``, that
is the feedback polynomial ``1 + x^t2 + ... + x^m`` (primitive over GF(2)). Source:
P. Alfke, "Efficient shift registers, LFSR counters, and long pseudo-random sequence
generators", Xilinx application note XAPP052 (1996), table 3; the table is the same
for XOR and XNOR feedback. Every entry is checked by the tests (period exactly
2**m - 1, two-valued periodic autocorrelation).
"""

MLS_MAX_ORDER = 20
"""Highest order :func:`mls` accepts with explicit ``taps`` (the register runs in a Python loop)."""


def mls(order: int, taps: Sequence[int] | None = None) -> NDArray[np.int8]:
    """Maximal-length sequence (m-sequence) of ``order`` m, length N = 2**m - 1, as ±1 values.

    A Fibonacci linear-feedback shift register: the first m bits are the initial fill
    (all ones), then ``s[n] = XOR of s[n - t] over the taps t``. With a primitive
    feedback polynomial the register runs through all 2**m - 1 non-zero states before
    it repeats (S. W. Golomb, "Shift Register Sequences", Holden-Day 1967, ch. III).
    Bit s maps to ``(-1)**s``: bit 0 is +1 and bit 1 is -1, so XOR of bits becomes the
    product of the ±1 values (what :func:`kasami_set` relies on).

    Properties (Golomb, ch. III): the period is exactly N; the sequence holds
    2**(m-1) bits 1 and 2**(m-1) - 1 bits 0, so with this mapping one more -1 than +1
    (the sum is -1); its periodic autocorrelation is N at lag 0 and -1 at every other lag.

    Parameters
    ----------
    order
        The register length m: 2..16 with the tabulated taps (:data:`MLS_TAPS`),
        2..20 with ``taps`` given.
    taps
        Feedback taps in 1..m including m itself, as in :data:`MLS_TAPS`; they must
        give a maximal-length sequence, which is checked.

    Returns
    -------
    numpy.ndarray
        int8 array of N values +1 and -1; it starts with m values -1 (the fill).
    """
    m = _whole(order, "MLS order")
    if taps is None:
        if m not in MLS_TAPS:
            raise WaveformError(
                f"no tabulated taps for MLS order {order}; use an order in 2..16 or give taps="
            )
        tap_set = MLS_TAPS[m]
    else:
        if not 2 <= m <= MLS_MAX_ORDER:
            raise WaveformError(f"MLS order must be in 2..{MLS_MAX_ORDER}, got {order}")
        tap_set = tuple(sorted({_whole(t, "MLS tap") for t in taps}, reverse=True))
        if not tap_set or tap_set[0] != m or tap_set[-1] < 1:
            raise WaveformError(f"MLS taps must lie in 1..{m} and include {m}, got {tuple(taps)}")
    n = (1 << m) - 1
    # Bit k-1 of `state` holds s[i-k] for k = 1..m when s[i] is computed next.
    mask = sum(1 << (t - 1) for t in tap_set)
    start = n  # all ones
    state = start
    bits = np.empty(n, dtype=np.int8)
    top = m - 1
    for i in range(n):
        bits[i] = (state >> top) & 1  # s[i], the oldest bit in the register
        state = ((state << 1) | ((state & mask).bit_count() & 1)) & n
        if state == start and i < n - 1:
            raise WaveformError(
                f"taps {tap_set} do not give a maximal-length sequence of order {m}: "
                f"the register repeats after {i + 1} steps, not 2**{m} - 1 = {n}"
            )
    return np.asarray(1 - 2 * bits, dtype=np.int8)


def kasami_set(order: int) -> NDArray[np.int8]:
    """The small Kasami set of even ``order`` m: 2**(m/2) ±1 sequences of length 2**m - 1.

    Construction (T. Kasami, "Weight distribution formula for some class of cyclic
    codes", Univ. of Illinois, Coordinated Science Lab., report R-285, 1966; in the
    form of D. V. Sarwate and M. B. Pursley, "Crosscorrelation properties of
    pseudorandom and related sequences", Proc. IEEE 68(5), 593-619, 1980):
    u is the m-sequence :func:`mls` (m), w the decimation ``w[k] = u[q k]`` with
    ``q = 2**(m/2) + 1``, an m-sequence of period 2**(m/2) - 1; the set is u and
    ``u XOR shift_j(w)`` for j = 0 .. 2**(m/2) - 2. With the ±1 mapping of
    :func:`mls`, XOR is the product ``u * roll(w, -j)``.

    Every periodic cross-correlation, and every autocorrelation off lag 0, takes only
    the values -1, -(2**(m/2) + 1) and 2**(m/2) - 1 (Kasami 1966; Sarwate and Pursley
    1980), so its magnitude is at most 2**(m/2) + 1 against a peak of 2**m - 1, which
    meets the Welch lower bound for a set of this size: several transmitters can fire
    at once and still be told apart.

    Parameters
    ----------
    order
        Even m in 4..16 (m = 2 would give just u and -u).

    Returns
    -------
    numpy.ndarray
        int8 array of shape (2**(m/2), 2**m - 1); row 0 is u itself.
    """
    m = _whole(order, "Kasami order")
    if m % 2 or not 4 <= m <= 16:
        raise WaveformError(f"the small Kasami set needs an even order in 4..16, got {order}")
    u = mls(m)
    n = u.size
    half = 1 << (m // 2)
    k = np.arange(n)
    # Decimating this phase of u can give the all-zero sequence (when the phase lies
    # in the subfield GF(2**(m/2))); the next phase of u never does.
    w = u[(half + 1) * k % n]
    if np.all(w == 1):
        w = u[((half + 1) * k + 1) % n]
    rows = [u] + [u * np.roll(w, -j) for j in range(half - 1)]
    return np.asarray(np.stack(rows), dtype=np.int8)


# --------------------------------------------------------------------------- pulses

ChirpMethod = Literal["linear", "hyperbolic"]
Window = Literal["tukey", "hann", "rect"]


def chirp_waveform(
    f0_hz: float,
    f1_hz: float,
    duration_s: float,
    sample_rate_hz: float,
    *,
    method: ChirpMethod = "linear",
    window: Window = "tukey",
    tukey_alpha: float = 0.25,
    name: str | None = None,
) -> Waveform:
    """A frequency sweep from ``f0_hz`` to ``f1_hz`` over ``duration_s``, shaped by a window.

    The sweep is :func:`scipy.signal.chirp` with ``phi=-90`` (a sine, phase 0 at
    t = 0, like :func:`modulate`), at ``t = n / sample_rate_hz`` for
    ``n = 0 .. round(duration_s * sample_rate_hz) - 1`` and ``t1 = duration_s``:

    - ``"linear"`` (LFM): ``f(t) = f0 + (f1 - f0) t / T``. Its matched-filter envelope
      is close to ``|sinc(B tau)|`` with ``B = |f1 - f0|`` when B T >> 1, so the -3 dB
      main lobe is about 0.886 / B wide (N. Levanon and E. Mozeson, "Radar Signals",
      Wiley 2004, ch. 4).
    - ``"hyperbolic"`` (HFM, linear-period modulation): ``f(t) = f0 f1 T / ((f0 - f1) t
      + f1 T)``, i.e. the period 1/f grows linearly with t; it tolerates Doppler
      (J. J. Kroszczynski, "Pulse compression by means of linear-period modulation",
      Proc. IEEE 57(7), 1260-1266, 1969).

    The window (:func:`scipy.signal.get_window`, symmetric) tapers the ends, which
    lowers the range sidelobes at the cost of a wider main lobe: ``"tukey"`` (flat
    middle, cosine tapers over the fraction ``tukey_alpha``), ``"hann"`` or ``"rect"``.

    Parameters
    ----------
    f0_hz, f1_hz
        Start and end frequency, Hz; both > 0 and below the Nyquist frequency.
    duration_s
        Length of the sweep, s (at least 2 samples).
    sample_rate_hz
        Sample rate, Hz.
    method
        ``"linear"`` or ``"hyperbolic"``.
    window
        ``"tukey"``, ``"hann"`` or ``"rect"``.
    tukey_alpha
        Tapered fraction of the Tukey window, 0..1 (0 is rectangular, 1 is Hann).
    name
        Waveform name; default ``"lfm"`` or ``"hfm"``.

    Returns
    -------
    Waveform
        Peak amplitude at most 1; ``carrier_hz`` is the centre frequency, the
        arithmetic mean (f0 + f1) / 2 for LFM (also its frequency at mid-pulse) and
        the geometric mean sqrt(f0 f1) for HFM, the centre of its band on a
        logarithmic frequency scale (at mid-pulse HFM is at the harmonic mean
        2 f0 f1 / (f0 + f1)); ``chip_s`` is 0.
    """
    if not (sample_rate_hz > 0 and duration_s > 0):
        raise WaveformError(f"duration ({duration_s} s) and sample rate ({sample_rate_hz} Hz) must be > 0")
    nyquist = sample_rate_hz / 2
    for label, f in (("f0_hz", f0_hz), ("f1_hz", f1_hz)):
        if not 0 < f < nyquist:
            raise WaveformError(
                f"chirp {label} = {f:g} Hz must lie between 0 and the Nyquist frequency {nyquist:g} Hz"
            )
    if method not in ("linear", "hyperbolic"):
        raise WaveformError(f"chirp method must be 'linear' or 'hyperbolic', got {method!r}")
    n = _pulse_samples(duration_s * sample_rate_hz, "the chirp")
    if n < 2:
        raise WaveformError(f"chirp of {duration_s:g} s is shorter than 2 samples at {sample_rate_hz:g} Hz")
    t = np.arange(n) / sample_rate_hz
    sweep = np.asarray(
        scipy.signal.chirp(t, f0=f0_hz, t1=duration_s, f1=f1_hz, method=method, phi=-90.0), dtype=float
    )
    centre_hz = (f0_hz + f1_hz) / 2 if method == "linear" else float(np.sqrt(f0_hz * f1_hz))
    return Waveform(
        samples=sweep * _window(window, n, tukey_alpha),
        sample_rate_hz=float(sample_rate_hz),
        carrier_hz=float(centre_hz),
        name=name if name is not None else ("lfm" if method == "linear" else "hfm"),
    )


def _window(window: str, n: int, tukey_alpha: float) -> NDArray[np.float64]:
    """Symmetric window of ``n`` points by name."""
    if window == "rect":
        return np.ones(n)
    if window == "hann":
        return np.asarray(scipy.signal.get_window("hann", n, fftbins=False), dtype=float)
    if window == "tukey":
        if not 0 <= tukey_alpha <= 1:
            raise WaveformError(f"tukey_alpha must lie in 0..1, got {tukey_alpha}")
        return np.asarray(scipy.signal.get_window(("tukey", tukey_alpha), n, fftbins=False), dtype=float)
    raise WaveformError(f"window must be 'tukey', 'hann' or 'rect', got {window!r}")


POLAROID_CYCLES = 16
POLAROID_CARRIER_HZ = 49.4e3
"""Polaroid 6500 series sonar ranging module (part 615077), technical specifications:
"the sonar transmit output is 16 cycles at a frequency of 49.4 kHz"."""


def tone_burst(
    cycles: int = POLAROID_CYCLES,
    carrier_hz: float = POLAROID_CARRIER_HZ,
    *,
    sample_rate_hz: float = 200e3,
    carrier: Carrier = "sine",
    name: str = "tone",
) -> Waveform:
    """A plain burst of ``cycles`` carrier cycles: by default the Polaroid ranging burst.

    The defaults are the transmit pulse of the Polaroid 6500 series sonar ranging
    module (technical specifications, part 615077: "16 cycles at a frequency of
    49.4 kHz"), the classic time-of-flight sensor of mobile robots. A burst is the
    one-bit code ``[+1]`` with ``cycles`` cycles per bit, so it is sampled exactly as
    :func:`modulate` does: ``round(cycles * sample_rate_hz / carrier_hz)`` samples,
    phase 0 at t = 0. Its envelope is rectangular, of duration T = cycles / carrier_hz;
    the matched-filter envelope is therefore a triangle of half-width T, without
    sidelobes (Levanon and Mozeson, "Radar Signals", 2004, ch. 3), and its -3 dB
    bandwidth is that of sinc²(f T): 0.886 / T.

    Parameters
    ----------
    cycles
        Number of carrier cycles, a positive whole number.
    carrier_hz
        Carrier frequency, Hz, below the Nyquist frequency.
    sample_rate_hz
        Sample rate, Hz.
    carrier
        ``"sine"`` or ``"square"``, as in :func:`modulate`.
    name
        Waveform name.

    Returns
    -------
    Waveform
        ``chip_s`` is 0 (not a code).
    """
    burst = modulate(
        [1],
        carrier_hz=carrier_hz,
        cycles_per_bit=cycles,
        sample_rate_hz=sample_rate_hz,
        carrier=carrier,
        name=name,
    )
    return replace(burst, chip_s=0.0)


# --------------------------------------------------------------------------- names

WAVEFORM_NAMES = (
    "barker{2,3,4,5,7,11,13}[b]",
    "golay{N}{a|b} (N = 2, 4, 8, ...)",
    "mls{2..16}",
    "kasami{4,6,..,16}[:k]",
    "tone{cycles}",
    "flip{cycles}",
    "polaroid",
    "lfm",
    "hfm",
)
"""The forms :func:`waveform_by_name` understands, for help texts and error messages."""

_CODE_PATTERNS = {
    "barker": re.compile(r"barker(\d+)([ab]?)"),
    "golay": re.compile(r"golay(\d+)([ab]?)"),
    "mls": re.compile(r"mls(\d+)"),
    "kasami": re.compile(r"kasami(\d+)(?::(\d+))?"),
}
_TONE_PATTERN = re.compile(r"tone(\d+)")
_FLIP_PATTERN = re.compile(r"flip(\d+)")


def _unknown_name(name: str) -> WaveformError:
    return WaveformError(f"unknown waveform name {name!r}; accepted forms: {', '.join(WAVEFORM_NAMES)}")


def _parse_code(name: str) -> tuple[str, NDArray[np.int8]] | None:
    """(canonical name, code) for a code name, None when ``name`` names no code family."""
    key = name.strip().lower()
    match = _CODE_PATTERNS["barker"].fullmatch(key)
    if match:
        length, variant = int(match[1]), "ab".index(match[2] or "a")
        return f"barker{length}{'b' if variant else ''}", barker(length, variant)
    match = _CODE_PATTERNS["golay"].fullmatch(key)
    if match:
        length, member = int(match[1]), match[2] or "a"
        a, b = golay_pair(length)
        return f"golay{length}{member}", a if member == "a" else b
    match = _CODE_PATTERNS["mls"].fullmatch(key)
    if match:
        return f"mls{int(match[1])}", mls(int(match[1]))
    match = _CODE_PATTERNS["kasami"].fullmatch(key)
    if match:
        order, member = int(match[1]), int(match[2] or 0)
        codes = kasami_set(order)
        if not 0 <= member < len(codes):
            raise WaveformError(f"kasami{order} has members 0..{len(codes) - 1}, not {member} (in {name!r})")
        return f"kasami{order}:{member}", codes[member]
    return None


def code_by_name(name: str) -> NDArray[np.int8]:
    """The bare ±1 code a name stands for: ``barker13``, ``barker4b``, ``golay16b``, ``mls7``, ``kasami6:2``.

    The forms are those of :func:`waveform_by_name` that name a code: ``barker{N}``
    with an optional variant letter (``a`` = variant 0, the default; ``b`` =
    variant 1), ``golay{N}{a|b}`` (``a`` when the letter is left out), ``mls{m}`` and
    ``kasami{m}:{k}`` (member k of :func:`kasami_set` (m), 0 = the m-sequence itself,
    when ``:k`` is left out). Case and surrounding blanks are ignored.
    """
    parsed = _parse_code(name)
    if parsed is None:
        key = name.strip().lower()
        pulses = (_TONE_PATTERN, _FLIP_PATTERN)
        if key in ("lfm", "hfm", "polaroid") or any(p.fullmatch(key) for p in pulses):
            raise WaveformError(f"waveform {name!r} is not a binary code")
        raise _unknown_name(name)
    return parsed[1]


def waveform_by_name(
    name: str,
    *,
    carrier_hz: float = 50e3,
    cycles_per_bit: int = 4,
    sample_rate_hz: float = 200e3,
    carrier: Carrier = "sine",
    chirp_bandwidth_hz: float = 20e3,
    chirp_duration_s: float = 1e-3,
    window: Window = "tukey",
) -> Waveform:
    """The pulse a short name stands for, e.g. for ``echoloc waveform NAME``.

    Names (case and surrounding blanks ignored; :data:`WAVEFORM_NAMES`):

    - codes, put on the carrier by :func:`modulate` with ``carrier_hz``,
      ``cycles_per_bit`` and ``carrier``: ``barker13``, ``barker4b`` (variant 1),
      ``golay16a`` / ``golay16b`` (the two halves of :func:`golay_pair`), ``mls7``,
      ``kasami6:2`` (member 2 of :func:`kasami_set`); see :func:`code_by_name`;
    - ``tone{cycles}``: :func:`tone_burst` of that many cycles at ``carrier_hz``;
    - ``flip{cycles}``: that many cycles at ``carrier_hz`` followed by as many inverted
      ones, the two-bit code ``[+1, -1]`` with ``cycles`` cycles per bit: the report's two
      pulse trains for envelope-zero detection (ch. 3.3), whose envelope passes through
      zero at the phase reversal, ``cycles / carrier_hz`` after emission; ``chip_s`` is
      one train. Not a code for :func:`code_by_name` (its cycles are part of the name);
    - ``polaroid``: the Polaroid burst, 16 cycles at 49.4 kHz whatever ``carrier_hz``;
    - ``lfm`` / ``hfm``: :func:`chirp_waveform` over ``chirp_bandwidth_hz`` during
      ``chirp_duration_s`` with ``window``, rising, centred on ``carrier_hz``: LFM from
      ``carrier_hz - B/2`` to ``carrier_hz + B/2``; HFM from
      ``f0 = sqrt(carrier_hz² + B²/4) - B/2`` to ``f0 + B``, so that its geometric
      centre sqrt(f0 f1) is ``carrier_hz`` too. ``carrier`` does not apply.

    The returned ``Waveform.name`` is the canonical spelling (``barker13``,
    ``barker4b``, ``golay16a``, ``kasami6:0``...), which this function accepts back.
    """
    key = name.strip().lower()
    parsed = _parse_code(key)
    if parsed is not None:
        canonical, code = parsed
        return modulate(
            code,
            carrier_hz=carrier_hz,
            cycles_per_bit=cycles_per_bit,
            sample_rate_hz=sample_rate_hz,
            carrier=carrier,
            name=canonical,
        )
    tone = _TONE_PATTERN.fullmatch(key)
    if tone:
        cycles = int(tone[1])
        return tone_burst(
            cycles, carrier_hz, sample_rate_hz=sample_rate_hz, carrier=carrier, name=f"tone{cycles}"
        )
    flip = _FLIP_PATTERN.fullmatch(key)
    if flip:
        return modulate(
            [1, -1],
            carrier_hz=carrier_hz,
            cycles_per_bit=int(flip[1]),
            sample_rate_hz=sample_rate_hz,
            carrier=carrier,
            name=f"flip{int(flip[1])}",
        )
    if key == "polaroid":
        return tone_burst(sample_rate_hz=sample_rate_hz, carrier=carrier, name="polaroid")
    if key in ("lfm", "hfm"):
        half_b = chirp_bandwidth_hz / 2
        if not 0 < half_b < carrier_hz:
            raise WaveformError(
                f"chirp_bandwidth_hz must lie between 0 and 2 * carrier_hz = {2 * carrier_hz:g}, "
                f"got {chirp_bandwidth_hz:g}"
            )
        if key == "lfm":
            f0, f1 = carrier_hz - half_b, carrier_hz + half_b
        else:
            f0 = float(np.sqrt(carrier_hz**2 + half_b**2)) - half_b
            f1 = f0 + chirp_bandwidth_hz
        return chirp_waveform(
            f0,
            f1,
            chirp_duration_s,
            sample_rate_hz,
            method="linear" if key == "lfm" else "hyperbolic",
            window=window,
        )
    raise _unknown_name(name)


# --------------------------------------------------------------------------- metrics


def _code_array(code: ArrayLike, what: str = "a code") -> NDArray[np.float64]:
    bits = np.asarray(code, dtype=float)
    if bits.ndim != 1 or bits.size == 0 or not np.all(np.abs(bits) == 1):
        raise WaveformError(f"{what} must be a non-empty sequence of +1 and -1")
    return bits


@dataclass(frozen=True)
class CodeMetrics:
    """Sidelobe figures of a bare ±1 code's aperiodic autocorrelation (no carrier).

    With ``r[k] = sum_n c[n] c[n+k]`` and N the length (Levanon and Mozeson, "Radar
    Signals", Wiley 2004, ch. 6; merit factor: M. J. E. Golay, "A class of finite
    binary sequences with alternate auto-correlation values equal to zero", IEEE
    Trans. Inf. Theory IT-18(3), 449-450, 1972):

    Attributes
    ----------
    length
        N.
    psl
        Peak sidelobe level ``max |r[k]|`` over k != 0 (0 for N = 1).
    pslr_ratio
        ``N / psl``: 13 for Barker-13 (inf when there is no sidelobe).
    pslr_db
        ``20 log10(pslr_ratio)``: 22.3 dB for Barker-13.
    merit_factor
        ``F = N² / (2 sum_{k>=1} r[k]²)``: 169/12 = 14.08 for Barker-13.
    isl_db
        Integrated sidelobe level ``10 log10(sum_{k != 0} r[k]² / N²) = -10 log10(F)``:
        -11.5 dB for Barker-13.
    """

    length: int
    psl: int
    pslr_ratio: float
    pslr_db: float
    merit_factor: float
    isl_db: float


def code_metrics(code: ArrayLike) -> CodeMetrics:
    """Peak sidelobe, merit factor and integrated sidelobe level of a ±1 code (see :class:`CodeMetrics`)."""
    bits = _code_array(code)
    n = bits.size
    r = np.rint(scipy.signal.correlate(bits, bits, mode="full")).astype(np.int64)
    side = r[n:]  # lags 1..N-1; the autocorrelation is even
    psl = int(np.max(np.abs(side))) if side.size else 0
    energy = float(np.sum(side.astype(float) ** 2))
    with np.errstate(divide="ignore"):
        pslr = n / psl if psl else float("inf")
        merit = n**2 / (2 * energy) if energy else float("inf")
    return CodeMetrics(
        length=n,
        psl=psl,
        pslr_ratio=float(pslr),
        pslr_db=float(20 * np.log10(pslr)),
        merit_factor=float(merit),
        isl_db=float(-10 * np.log10(merit)),
    )


@dataclass(frozen=True)
class WaveformMetrics:
    """Figures of merit of a pulse's matched-filter output (see :func:`waveform_metrics`).

    Attributes
    ----------
    pslr_db
        Peak-to-sidelobe ratio of the correlation envelope, dB (positive):
        ``20 log10(pslr_ratio)``.
    pslr_ratio
        Envelope peak over the largest envelope value outside the main lobe (the main
        lobe reaches from the peak down to the first local minimum on each side); inf
        when the envelope has no sidelobe.
    islr_db
        Integrated sidelobe level, dB (negative): envelope energy outside the main
        lobe over the energy inside it.
    mainlobe_width_s
        Full width of the main lobe where the envelope is above peak / sqrt(2) (-3 dB), s.
    range_resolution_m
        ``speed_of_sound_m_s * mainlobe_width_s / 2`` (two-way path), m.
    duration_s
        Duration of the emitted waveform, s.
    bandwidth_hz
        -3 dB bandwidth of the received signal (the waveform itself when no response
        is given), Hz: from the lowest to the highest frequency where its power
        spectrum reaches half its peak. For a smooth spectrum (burst, chirp) the
        usual half-power width; for a phase code, whose spectrum ripples, narrower
        than the chip rate 1 / chip_s, so ``time_bandwidth`` is then not the
        compression ratio.
    time_bandwidth
        ``duration_s * bandwidth_hz``.
    peak_lag_s
        Lag of the envelope peak, s: 0 for the autocorrelation; with a response and
        the sent template, the delay the response adds to a time-of-flight estimate.
    """

    pslr_db: float
    pslr_ratio: float
    islr_db: float
    mainlobe_width_s: float
    range_resolution_m: float
    duration_s: float
    bandwidth_hz: float
    time_bandwidth: float
    peak_lag_s: float


_MAX_ENVELOPE_POINTS = 1 << 22
"""Cap on the oversampled correlation grid; beyond it the oversampling factor shrinks."""


def _samples(values: ArrayLike, what: str) -> NDArray[np.float64]:
    try:
        x = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise WaveformError(f"{what} must be a 1-D array of numbers") from None
    if x.ndim != 1 or x.size == 0:
        raise WaveformError(f"{what} must be a non-empty 1-D array, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise WaveformError(f"{what} holds non-finite values")
    if not np.any(x):
        raise WaveformError(f"{what} is zero everywhere")
    return x


def _correlation_envelope(
    received: NDArray[np.float64], template: NDArray[np.float64], oversample: int
) -> tuple[NDArray[np.float64], int, int]:
    """Envelope of the analytic cross-correlation on a grid ``oversample`` times finer.

    ``c[k] = sum_n received[n + k] template[n]`` for the lags where the sampled
    correlation is defined, -(len(template) - 1) .. len(received) - 1. Its analytic
    signal is formed in the frequency domain (one-sided spectrum doubled, DC and
    Nyquist bins kept once: S. L. Marple, "Computing the discrete-time analytic signal
    via FFT", IEEE Trans. Signal Process. 47(9), 2600-2603, 1999) and interpolated
    band-limited by zero-padding the spectrum.

    Returns (envelope, index of lag 0 in the envelope, oversampling factor used).
    """
    n_r, n_t = received.size, template.size
    nfft = int(scipy.fft.next_fast_len(2 * (n_r + n_t), real=True))
    factor = max(1, min(oversample, _MAX_ENVELOPE_POINTS // nfft))
    spectrum = np.asarray(scipy.fft.rfft(received, nfft))
    spectrum = spectrum * np.conj(np.asarray(scipy.fft.rfft(template, nfft)))
    half = nfft // 2  # nfft is even (2 * ...), so bin `half` is the Nyquist bin
    one_sided = np.zeros(factor * nfft, dtype=complex)
    one_sided[0] = spectrum[0]
    one_sided[1:half] = 2 * spectrum[1:half]
    one_sided[half] = spectrum[half]
    analytic = np.asarray(scipy.fft.ifft(one_sided)) * factor
    negative = analytic[analytic.size - (n_t - 1) * factor :] if n_t > 1 else analytic[:0]
    envelope = np.abs(np.concatenate((negative, analytic[: (n_r - 1) * factor + 1])))
    return envelope, (n_t - 1) * factor, factor


def _half_power_band(x: NDArray[np.float64], sample_rate_hz: float) -> float:
    """-3 dB bandwidth of ``x``, Hz: from the lowest to the highest frequency where the power spectrum
    reaches half its peak (the "x dB bandwidth" of Recommendation ITU-R SM.328 with x = 3, as measured
    in ITU-R SM.443, annex 2), on a zero-padded FFT with the crossings interpolated linearly."""
    nfft = int(scipy.fft.next_fast_len(max(16 * x.size, 4096), real=True))
    power = np.abs(np.asarray(scipy.fft.rfft(x, nfft))) ** 2
    level = power.max() / 2
    above = np.nonzero(power >= level)[0]
    i, j = int(above[0]), int(above[-1])
    low = i - (power[i] - level) / (power[i] - power[i - 1]) if i > 0 else 0.0
    high = j + (power[j] - level) / (power[j] - power[j + 1]) if j < power.size - 1 else float(j)
    return float((high - low) * sample_rate_hz / nfft)


def waveform_metrics(
    waveform: Waveform,
    *,
    response: ArrayLike | None = None,
    template: Literal["sent", "received"] | ArrayLike | None = None,
    speed_of_sound_m_s: float = 343.2,
    oversample: int = 8,
) -> WaveformMetrics:
    """Peak-to-sidelobe ratio, sidelobe level, main-lobe width and bandwidth of a pulse's matched filter.

    The received signal is ``waveform.samples`` convolved with ``response`` (an
    impulse response at the waveform's sample rate, e.g. transmitter and receiver
    transducers in series; without it, the waveform itself). It is cross-correlated
    with a template, as the report's matched filter does (ch. 3.4; docs/METHOD.md):

    - ``template=None`` or ``"sent"``: the emitted waveform, the report's SENT
      template. With a response this filter is mismatched: the output is the
      waveform's autocorrelation smeared by the response. (The report expected a
      PSLR of 13 for Barker-13 and measured 9:1, ch. 4, which it put down to the
      transmitted signal not being exactly the Barker code.)
    - ``"received"``: the received signal itself, the matched case (the best a
      template measured through the same transducers, like the report's DIRECT,
      can do).
    - an array: any other template at the same sample rate.

    The figures are read off the envelope (modulus of the analytic signal) of the
    correlation, interpolated band-limited on a grid ``oversample`` times finer than
    the sample spacing (fewer when that grid would exceed 2**22 points), so widths
    are not limited by the sampling:

    - main lobe: from the envelope peak down to the first local minimum on each side;
    - PSLR: peak / largest envelope value outside the main lobe (Levanon and Mozeson,
      "Radar Signals", Wiley 2004, ch. 6; 13 = 22.3 dB for Barker-13 as the report
      says, ch. 3.4.3.3);
    - ISLR: ``10 log10(sum of envelope² outside the main lobe / sum inside)``, the
      continuous-time analogue of the code's ISL (for Barker-13 on a carrier the two
      agree, -11.5 dB, since the envelope is piecewise linear between the code's
      correlation values, which alternate 0 and 1);
    - main-lobe width: full width at peak / sqrt(2) (-3 dB), crossings interpolated
      linearly; e.g. 2 T (1 - 1/sqrt 2) = 0.586 T for a rectangular burst of
      duration T (triangular envelope), about 0.886 / B for a linear chirp of
      bandwidth B;
    - range resolution: ``c * width / 2`` (two-way path; M. I. Skolnik, "Introduction
      to Radar Systems", 3rd ed., 2001, with the -3 dB width as the resolved
      pulse length).

    Parameters
    ----------
    waveform
        The emitted pulse.
    response
        Optional impulse response of the transducer pair, 1-D, at ``waveform.sample_rate_hz``.
    template
        ``None``/``"sent"``, ``"received"`` or an array (see above).
    speed_of_sound_m_s
        Speed of sound for the range resolution, m/s (343.2 m/s: dry air at 20 °C).
    oversample
        Refinement of the correlation grid, a positive whole number.

    Returns
    -------
    WaveformMetrics
    """
    sent = _samples(waveform.samples, f"waveform {waveform.name!r}")
    fs = float(waveform.sample_rate_hz)
    if not fs > 0:
        raise WaveformError(f"waveform sample rate must be > 0, got {fs}")
    if not speed_of_sound_m_s > 0:
        raise WaveformError(f"speed_of_sound_m_s must be > 0, got {speed_of_sound_m_s}")
    factor = _whole(oversample, "oversample")
    if factor < 1:
        raise WaveformError(f"oversample must be >= 1, got {oversample}")
    received = sent
    if response is not None:
        h = _samples(response, "response")
        received = np.asarray(scipy.signal.convolve(sent, h, mode="full"), dtype=float)
    if template is None or (isinstance(template, str) and template == "sent"):
        reference = sent
    elif isinstance(template, str) and template == "received":
        reference = received
    elif isinstance(template, str):
        raise WaveformError(f"template must be 'sent', 'received' or an array, got {template!r}")
    else:
        reference = _samples(template, "template")

    envelope, zero, factor = _correlation_envelope(received, reference, factor)
    i0 = int(np.argmax(envelope))
    peak, shift = float(envelope[i0]), 0.0
    if 0 < i0 < envelope.size - 1:  # parabola through the three samples about the peak
        y0, y1, y2 = envelope[i0 - 1 : i0 + 2]
        curvature = y0 - 2 * y1 + y2
        if curvature < 0:
            shift = 0.5 * (y0 - y2) / curvature
            peak = float(y1 - 0.25 * (y0 - y2) * shift)

    slope = np.diff(envelope)
    rising = np.nonzero(slope[i0:] > 0)[0]
    right = i0 + int(rising[0]) if rising.size else envelope.size - 1
    falling = np.nonzero(slope[:i0] < 0)[0]
    left = int(falling[-1]) + 1 if falling.size else 0
    outside = np.concatenate((envelope[:left], envelope[right + 1 :]))
    sidelobe = float(outside.max()) if outside.size else 0.0
    inside_energy = float(np.sum(envelope[left : right + 1] ** 2))
    outside_energy = float(np.sum(outside**2))

    level = peak / np.sqrt(2)
    below_left = np.nonzero(envelope[:i0] < level)[0]
    below_right = np.nonzero(envelope[i0:] < level)[0]
    if not (below_left.size and below_right.size):
        raise WaveformError(
            f"the correlation envelope of {waveform.name!r} does not fall to -3 dB on both sides of its peak"
        )
    i = int(below_left[-1])
    x_left = i + (level - envelope[i]) / (envelope[i + 1] - envelope[i])
    j = i0 + int(below_right[0])
    x_right = j - 1 + (envelope[j - 1] - level) / (envelope[j - 1] - envelope[j])
    width_s = float((x_right - x_left) / (factor * fs))

    with np.errstate(divide="ignore"):
        ratio = peak / sidelobe if sidelobe > 0 else float("inf")
        islr_db = float(10 * np.log10(outside_energy / inside_energy))
    bandwidth_hz = _half_power_band(received, fs)
    duration_s = sent.size / fs
    return WaveformMetrics(
        pslr_db=float(20 * np.log10(ratio)),
        pslr_ratio=float(ratio),
        islr_db=islr_db,
        mainlobe_width_s=width_s,
        range_resolution_m=speed_of_sound_m_s * width_s / 2,
        duration_s=duration_s,
        bandwidth_hz=bandwidth_hz,
        time_bandwidth=duration_s * bandwidth_hz,
        peak_lag_s=float((i0 + shift - zero) / (factor * fs)),
    )


def peak_cross_correlation(
    a: ArrayLike | Waveform, b: ArrayLike | Waveform, *, periodic: bool = False
) -> float:
    """Largest magnitude of the cross-correlation of ``a`` and ``b``, normalised to 1 for ``a = b``.

    Codes or sample arrays: ``max_k |sum_n a[n] b[n + k]| / sqrt(E_a E_b)`` with
    ``E = sum x²`` (for two ±1 codes of length N the divisor is N), aperiodic (zero
    outside the sequences) or, with ``periodic=True``, cyclic (``b[(n + k) mod N]``,
    equal lengths; the correlation of sequences sent back to back, as in Sarwate and
    Pursley, Proc. IEEE 68(5), 1980). By the Cauchy-Schwarz inequality the value is at
    most 1, reached when b is a shifted copy of a (a multiple, aperiodically).

    Two :class:`Waveform` values (same sample rate): aperiodic only, and the
    correlation's envelope is used (modulus of its analytic signal, oversampled x8 as
    in :func:`waveform_metrics`), so the carrier phase does not matter.
    """
    if isinstance(a, Waveform) or isinstance(b, Waveform):
        if not (isinstance(a, Waveform) and isinstance(b, Waveform)):
            raise WaveformError("compare two Waveforms or two arrays, not a mix of both")
        if a.sample_rate_hz != b.sample_rate_hz:
            raise WaveformError(
                f"waveforms sampled at {a.sample_rate_hz:g} Hz and {b.sample_rate_hz:g} Hz cannot be compared"
            )
        if periodic:
            raise WaveformError("the periodic cross-correlation applies to codes, not to Waveforms")
        x, y = _samples(a.samples, f"waveform {a.name!r}"), _samples(b.samples, f"waveform {b.name!r}")
        envelope, _, _ = _correlation_envelope(y, x, 8)
        peak = float(envelope.max())
    else:
        x, y = _samples(a, "a"), _samples(b, "b")
        if periodic:
            if x.size != y.size:
                raise WaveformError(f"periodic correlation needs equal lengths, got {x.size} and {y.size}")
            cyclic = scipy.fft.ifft(np.conj(scipy.fft.fft(x)) * scipy.fft.fft(y))
            peak = float(np.max(np.abs(np.asarray(cyclic).real)))
        else:
            peak = float(np.max(np.abs(scipy.signal.correlate(y, x, mode="full"))))
    return peak / float(np.sqrt(np.sum(x**2) * np.sum(y**2)))
