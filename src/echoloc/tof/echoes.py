"""Time of flight: from received frames to echoes (tof, amplitude, SNR) per receiver.

The matched filter lives here with the types every estimator returns; envelope
estimators are in :mod:`echoloc.tof.envelopes` and the registry of all of them in
:mod:`echoloc.tof.estimators`.

``matched``
    Matched filter. The frame is correlated with the emitted pulse (the SENT
    template) through FFTs, and the correlation is made analytic in the same pass
    (negative frequencies removed), so its magnitude is the envelope and its phase
    the carrier phase. Echoes are extracted one by one, strongest first, by
    subtracting the template's own autocorrelation at the fitted delay (CLEAN),
    which removes the code's sidelobes with the echo and uncovers weaker and
    overlapping echoes. Every echo is then re-fitted with the others removed (two
    passes of successive refinement). Each delay is the envelope's peak refined by
    the carrier phase at the peak; the half-cycle ambiguity of the phase (an echo
    may come back inverted) is resolved by the envelope. Echoes whose main lobes
    overlap are fitted jointly (least squares of ``sum_k a_k R(m - tau_k)``, complex
    amplitudes then real ones), and the number of echoes in a crowded stretch is
    chosen by a penalised cost among alternatives: each echo half a carrier cycle
    off with its sign flipped, each left out, the stretch read afresh as two echoes
    (:meth:`_Clean._choose_overlapping`, :meth:`_Clean._choose_order`).

    Detection follows each channel's noise (its power the median of the correlation's, see
    below): an echo is kept when its output SNR reaches ``threshold_db``. The dynamic range
    (``dynamic_range_db``) is local: it drops what a strong echo leaves within the
    template's support around it (sidelobes, the residue of an imperfect subtraction), not
    what lies beyond, so a strong direct path or cross-talk sets no scale for the echoes a
    template's length after it (:meth:`_Clean._below_floor`, :func:`_local_strongest`,
    :func:`finish_channel`).

    Speed: frames are processed in batches (:func:`matched_filter_batch`). The
    correlation of all channels is one single-precision FFT pass; a batch path in
    compiled loops (:mod:`echoloc.tof._echoes_kernels`, stated in numpy by
    :func:`_isolated_echoes`) fits isolated echoes and clusters of resolved echoes
    with the same formulas, and hands CLEAN only the channels whose correlation its
    model does not explain. CLEAN runs in compiled loops too, one call a channel
    (:class:`_Clean` with ``compiled=False`` is its Python statement), on the hard
    channels' double-precision correlation computed in one call; its complex-amplitude
    fits step in the frame turning with the carrier and stop at 1e-3 samples or once a
    step gains less than 1 % of the cost, since they only choose the basin the
    real-amplitude fit settles in.

Conventions: ``tof_s`` is the delay from emission start to the echo's arrival
(docs/FORMATS.md), whatever the estimator. ``amplitude`` is the echo's peak amplitude in
sample units (the least-squares scale of the template). ``snr_db`` is the
matched-filter output SNR, ``10 log10(|a|^2 / P)``, with ``P`` the mean noise power of
the normalised analytic correlation, estimated robustly from the frame (for the
threshold estimator, the same ratio on the signal's own envelope).
"""

from __future__ import annotations

import cmath
import itertools
import math
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property, partial
from typing import Any, NamedTuple

import numpy as np
import scipy.fft
from numpy.typing import NDArray

from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording
from echoloc.tof.templates import Template

_LN2 = float(np.log(2.0))


THRESHOLD_DB_LIMIT = 300.0
"""The largest detection threshold, dB either way: 10^30 in power. No correlation sample of
a float32 frame stands that far above (or below) its noise, and beyond it, about 3080 dB,
the power ratio is no longer a float."""


PRECISION_DB = 100.0
"""Echoes more than this below their channel's strongest are dropped, near it or not: what the
frames resolve (16-bit samples span 96 dB; the single-precision correlation's rounding grows
from 1e-7 of its strongest value over the FFTs' stages), and in a noiseless frame, where the
threshold stops nothing, the far tails of band-limited echoes (110 dB down 230 samples away).
Far below the echoes the local dynamic range keeps (``EchoOptions.dynamic_range_db``)."""
_PRECISION_POWER = 10 ** (-PRECISION_DB / 10)
_PRECISION_AMPLITUDE = 10 ** (-PRECISION_DB / 20)


@dataclass(frozen=True)
class EchoOptions:
    """Options of every estimator.

    threshold_db
        Detection threshold on the output SNR (see module doc), dB. The default of
        14 dB keeps the false-alarm probability per sample of Rayleigh noise at
        exp(-10**1.4) = 1.4e-11.
    blanking_s
        Echoes arriving earlier than this (transmitter ring-down, direct coupling)
        are dropped, s.
    max_echoes
        At most this many echoes per receiver and frame.
    dynamic_range_db
        Echoes weaker by more than this than an echo that overlaps them are dropped:
        the residue of an imperfect subtraction (a template that differs from the echo,
        a delay or amplitude slightly off) and a strong echo's sidelobes, not echoes, dB.
        That residue scales with the strong echo and lies within the correlation's support
        around it, the template's length (:attr:`MatchedFilter.support_s`); so the matched
        filter holds an echo only to the echoes within that of it. Detection elsewhere
        follows the noise alone (``threshold_db`` over each channel's own noise power):
        the direct path or cross-talk, however strong, sets no scale for the echoes after
        it once they are a template's length away, and an echo 80 dB below it is found if
        it stands above the noise. (The envelope estimators keep one floor per channel,
        below its strongest echo.)
    refine_passes
        Passes of re-fitting each echo with the others removed (matched filter).
    threshold_fraction
        The threshold estimator's level is at least this fraction of the channel's
        strongest envelope sample, so that clean data is not cut at its noise floor.
    template
        The matched filter's template (:mod:`echoloc.tof.templates`: DIRECT, a recorded
        echo); None: the recording's own waveform (SENT).
    workers
        Threads the matched filter spreads a frame's (or a batch's) channels over; -1:
        one a core. The answers do not depend on it: channels are independent.
    """

    threshold_db: float = 14.0
    blanking_s: float = 0.0
    max_echoes: int = 16
    dynamic_range_db: float = 40.0
    refine_passes: int = 3
    threshold_fraction: float = 0.1
    template: Template | None = None
    workers: int = 1

    def __post_init__(self) -> None:
        if self.workers < 1 and self.workers != -1:
            raise EchoLocError(f"workers must be >= 1 (or -1: one a core), got {self.workers}")
        if not abs(self.threshold_db) <= THRESHOLD_DB_LIMIT:
            raise EchoLocError(
                f"threshold_db must be between {-THRESHOLD_DB_LIMIT:g} and {THRESHOLD_DB_LIMIT:g} dB, "
                f"got {self.threshold_db:g}"
            )

    @property
    def threads(self) -> int:
        """:attr:`workers` as a thread count (-1: the machine's cores)."""
        return max(os.cpu_count() or 1, 1) if self.workers == -1 else self.workers


@dataclass(frozen=True, eq=False)
class ChannelEchoes:
    """Echoes of one receiver in one frame, in ascending ``tof_s``."""

    tof_s: NDArray[np.float64]
    amplitude: NDArray[np.float64]
    snr_db: NDArray[np.float64]

    @staticmethod
    def empty() -> ChannelEchoes:
        return ChannelEchoes(np.zeros(0), np.zeros(0), np.zeros(0))


@dataclass(frozen=True, eq=False)
class FrameEchoes:
    """Echoes of every receiver in one frame."""

    frame: int
    time_s: float
    speed_of_sound_m_s: float
    channels: tuple[ChannelEchoes, ...]


# --- analytic correlation ----------------------------------------------------------


def analytic_weights(n_fft: int) -> NDArray[np.float64]:
    """Weights on the rfft bins that make the inverse complex FFT analytic."""
    weights = np.full(n_fft // 2 + 1, 2.0)
    weights[0] = 1.0
    if n_fft % 2 == 0:
        weights[-1] = 1.0
    return weights


_ACF_TABLES: dict[tuple[Any, ...], NDArray[np.complex128]] = {}
"""The sub-sample tables last built (:attr:`MatchedFilter.acf_table`), least recently used
first, up to :data:`_ACF_TABLES_BYTES` in all."""
_ACF_TABLES_BYTES = 16 << 20
"""What the kept tables may take: 19 of the default head's (0.84 MiB each). A table is
``oversample x (2 half_width + 1) x 16`` bytes, which grows with the template (256 MiB for a
65 520-sample one); one larger than this is not kept."""
_ACF_TABLES_LOCK = threading.Lock()


@dataclass(frozen=True, eq=False)
class MatchedFilter:
    """Everything the matched filter reuses for frames of one shape and template.

    The template spectrum, the FFT length and a table of the template's analytic
    autocorrelation at ``oversample`` sub-sample shifts are computed once.

    With ``decimation`` D, the correlation is kept at every D-th lag: its lags, the
    tables, the main lobe and the phase rate are in units of D samples (``lag_rate_hz``).
    The inverse FFT then has N/D points: the rfft bins fold onto N/D bins, which gives
    the analytic correlation's values at those lags exactly. For D = 2 nothing is lost:
    an analytic signal's spectrum spans half the sample rate, so its even samples
    determine it (complex sampling at fs/2; e.g. Lyons, *Understanding Digital Signal
    Processing*, 3rd ed., sec. 8.9).
    """

    template: NDArray[np.float64]
    n_samples: int
    sample_rate_hz: float
    oversample: int = 256
    arrival_s: float = 0.0  # where, within the template, the echo arrives (templates.Template)
    decimation: int = 1

    def __post_init__(self) -> None:
        if self.decimation < 1:
            raise EchoLocError(f"the matched filter's decimation must be >= 1, got {self.decimation}")

    @cached_property
    def lag_rate_hz(self) -> float:
        """Lags of the correlation per second: the sample rate over the decimation."""
        return self.sample_rate_hz / self.decimation

    @cached_property
    def n_lags(self) -> int:
        """Lags of the correlation of a frame: 0, D, 2D, ... below ``n_samples``."""
        return -(-self.n_samples // self.decimation)

    def first_lag(self, blanking_s: float) -> int:
        """The first lag at or after ``blanking_s`` (the echoes before it are blanked)."""
        return math.ceil(blanking_s * self.lag_rate_hz)

    @cached_property
    def kernel_constants_memo(self) -> dict[tuple[float, ...], Any]:
        """The compiled batch path's per-options arguments, built once each (:func:`_kernel_constants`)."""
        return {}

    @cached_property
    def kernel_arguments_memo(self) -> dict[tuple[int, int, int], Any]:
        """The compiled call's arguments per options, threads, channels (:func:`_fixed_kernel_arguments`)."""
        return {}

    @cached_property
    def n_fft(self) -> int:
        """The FFT length: no wrap-around into the frame's lags, fast, a multiple of the decimation."""
        n = int(scipy.fft.next_fast_len(self.n_samples + len(self.template), real=True))
        while n % self.decimation:
            n = int(scipy.fft.next_fast_len(n + 1, real=True))
        return n

    @cached_property
    def n_ifft(self) -> int:
        """The inverse FFT's length: N/D, whose first ``n_lags`` outputs are the correlation."""
        return self.n_fft // self.decimation

    @cached_property
    def energy(self) -> float:
        return float(np.sum(self.template**2))

    @cached_property
    def _template_spectrum(self) -> NDArray[np.complex128]:
        """W(f): the template's rfft at the correlation length, computed once."""
        return np.asarray(scipy.fft.rfft(self.template, self.n_fft))

    @cached_property
    def _template_power(self) -> NDArray[np.float64]:
        """|W(f)|², the spectrum of the template's autocorrelation."""
        return np.asarray(np.abs(self._template_spectrum) ** 2)

    @cached_property
    def _spectrum(self) -> NDArray[np.complex128]:
        """conj(W(f)) times the analytic weights, divided by the template's energy and by the
        decimation (the shorter inverse FFT's normalisation)."""
        weights = analytic_weights(self.n_fft) / (self.energy * self.decimation)
        return np.asarray(np.conj(self._template_spectrum) * weights)

    @cached_property
    def _spectrum_single(self) -> NDArray[np.complex64]:
        """:attr:`_spectrum` in single precision, for the correlation's FFTs."""
        return np.asarray(self._spectrum, dtype=np.complex64)

    def _weigh_and_fold(self, spectrum: NDArray[Any], weights: NDArray[Any]) -> NDArray[Any]:
        """The product of the frames' spectrum (..., bins) and ``weights``, its bins summed
        modulo N/D (zero-padded to N/D when shorter), in the precision of the two: the inverse
        FFT of N/D points then gives every D-th lag. One compiled pass
        (:func:`echoloc.tof._echoes_kernels.weigh_and_fold`): numpy's product, fold and copy, each
        a pass over the spectrum with its own call, took longer."""
        from echoloc.tof import _echoes_kernels as kernels  # numba: imported (and compiled) on first use

        folded = np.empty((*spectrum.shape[:-1], self.n_ifft), dtype=np.result_type(spectrum, weights))
        rows = spectrum.reshape(-1, spectrum.shape[-1])
        kernels.weigh_and_fold(rows, weights, folded.reshape(-1, self.n_ifft))
        return folded

    @cached_property
    def half_width(self) -> int:
        """Lags kept on either side of an autocorrelation peak (template length + 2 samples)."""
        return -(-(len(self.template) + 2) // self.decimation)

    @cached_property
    def residue_lags(self) -> int:
        """How far what an echo leaves in the correlation reaches on either side of its peak, lags:
        the template's length (:attr:`half_width`), where its sidelobes end, and a main lobe
        more. An echo is band-limited where the template may not be (a pulse's abrupt end or
        phase flips, interpolated, ring on past it by about the band's inverse, a main lobe), so
        what its subtraction leaves reaches that far: the residue of a pyroomacoustics direct
        path 97 dB above the noise stood 23 dB above it one lag past the template's length,
        below it five lags on. The dynamic range holds an echo only to the echoes within this
        of it (:meth:`_Clean._below_floor`, :func:`_local_strongest`, :func:`finish_channel`)."""
        return self.half_width + math.ceil(self.mainlobe_lags)

    @cached_property
    def support_s(self) -> float:
        """:attr:`residue_lags` in seconds."""
        return self.residue_lags / self.lag_rate_hz

    def _lags_of(self, full: NDArray[np.complex128]) -> NDArray[np.complex128]:
        """Lags -half_width..half_width (in units of D samples) of a full-rate circular sequence."""
        lags = np.arange(-self.half_width, self.half_width + 1) * self.decimation
        return np.asarray(full[..., lags % self.n_fft])

    @cached_property
    def acf_table(self) -> NDArray[np.complex128]:
        """Analytic autocorrelation for shifts j/oversample, lags -half_width..half_width.

        Row j holds R(m - j/U) for m = -H..H (in lags), with R(0) = 1 for j = 0.

        Building it (256 phase ramps and inverse FFTs for the default head) is the most of
        preparing a stream's session, so the tables last built are kept (up to
        :data:`_ACF_TABLES_BYTES`) by what defines them (the template, the FFT length, the
        oversampling, the decimation): a sender that starts its session again, or the head
        ``warm_kernels`` prepared, finds its table made. Each filter gets its own copy (cheap
        beside building it).
        """
        key = (self.template.tobytes(), self.template.dtype.str, self.n_fft, self.oversample, self.decimation)
        with _ACF_TABLES_LOCK:
            kept = _ACF_TABLES.pop(key, None)
            if kept is not None:
                _ACF_TABLES[key] = kept  # now the most recently used
                return kept.copy()
        table = self._built_acf_table()
        if table.nbytes <= _ACF_TABLES_BYTES:
            with _ACF_TABLES_LOCK:
                _ACF_TABLES.pop(key, None)  # another thread's, built meanwhile: made the newest
                _ACF_TABLES[key] = table.copy()
                total = sum(t.nbytes for t in _ACF_TABLES.values())
                while total > _ACF_TABLES_BYTES:
                    total -= _ACF_TABLES.pop(next(iter(_ACF_TABLES))).nbytes  # least recently used
        return table

    def _built_acf_table(self) -> NDArray[np.complex128]:
        """:attr:`acf_table`, computed."""
        n_fft = self.n_fft
        power = self._template_power
        freqs = np.arange(n_fft // 2 + 1) / n_fft  # cycles per sample
        shifts = np.arange(self.oversample) * self.decimation / self.oversample  # samples
        spectra = power * analytic_weights(n_fft) / self.energy
        rows = scipy.fft.ifft(spectra * np.exp(-2j * np.pi * freqs * shifts[:, None]), n_fft, axis=-1)
        return np.ascontiguousarray(self._lags_of(rows))

    @cached_property
    def phase_rate_rad_per_lag(self) -> float:
        """d(arg R)/d(lag) at lag 0: 2 pi times the power-weighted mean frequency, rad per lag."""
        power = self._template_power
        freqs = np.arange(len(power)) / self.n_fft
        return float(2 * np.pi * self.decimation * np.sum(freqs * power) / np.sum(power))

    @cached_property
    def _autocorrelation_full(self) -> NDArray[np.complex128]:
        """The analytic autocorrelation at every sample, circularly (n_fft values, lag 0 first)."""
        power = self._template_power
        return np.asarray(scipy.fft.ifft(power * analytic_weights(self.n_fft) / self.energy, self.n_fft))

    @cached_property
    def autocorrelation(self) -> NDArray[np.complex128]:
        """Analytic autocorrelation R(m) for lags -half_width..half_width (row 0 of the table)."""
        return self._lags_of(self._autocorrelation_full)

    @cached_property
    def mainlobe_lags(self) -> float:
        """Full width of the autocorrelation envelope's main lobe at -6 dB, in lags.

        Measured on every sample and divided by the decimation (the physical width, not
        rounded to whole lags); from the autocorrelation alone, so asking for it does not
        build the sub-sample table.
        """
        envelope = np.abs(self._autocorrelation_full)
        n = len(envelope)
        # Walk out from the peak (lag 0, circularly) to the first lag below half on each side.
        right = 0
        while right + 1 < n // 2 and envelope[right + 1] >= 0.5:
            right += 1
        left = 0
        while left - 1 > -(n // 2) and envelope[left - 1] >= 0.5:
            left -= 1
        return float(right - left + 1) / self.decimation

    @cached_property
    def acf_energy(self) -> float:
        """Energy of the analytic autocorrelation over its lags, ``sum |R(m)|^2``."""
        return float(np.sum(np.abs(self.autocorrelation) ** 2))

    @cached_property
    def sidelobe_envelope(self) -> NDArray[np.float64]:
        """:func:`_sidelobe_envelope`, computed once."""
        return _sidelobe_envelope(self)

    def correlate(self, frames: NDArray[np.floating], threads: int | None = None) -> NDArray[np.complex128]:
        """Analytic correlation of frames (..., n_samples) with the template, (..., n_lags).

        Lag k is a delay of k D samples (an echo arriving k D samples after emission
        peaks at k); normalised so that an echo ``a * template`` gives ``a`` there.
        The FFTs take at most ``threads`` threads (None: one a core), and fewer on few
        rows (:func:`fft_workers`).
        """
        workers = fft_workers(threads or os.cpu_count() or 1, math.prod(np.shape(frames)[:-1]))
        spectrum = scipy.fft.rfft(frames, self.n_fft, axis=-1, workers=workers)
        folded = self._weigh_and_fold(spectrum, self._spectrum)
        full = scipy.fft.ifft(folded, axis=-1, overwrite_x=True, workers=workers)
        return np.asarray(full[..., : self.n_lags])

    def correlate_single(self, frames: NDArray[np.floating]) -> NDArray[np.complex64]:
        """:meth:`correlate` in single precision: faster, for detection and fits.

        Rounding errors are ~1e-7 of the frame's strongest correlation, spread over every
        lag like white noise: 1e-3 of an echo 80 dB weaker. They stay far below the noise of
        any recorded frame (float32 samples, or 16-bit ones: 96 dB), and where they do not,
        the noise power, estimated from the correlation itself, includes them. The fits read
        the samples they need in double precision.
        """
        return self.correlate_single_rows(frames)[..., : self.n_lags]

    def correlate_single_rows(self, frames: NDArray[np.floating], workers: int = 1) -> NDArray[np.complex64]:
        """:meth:`correlate_single` as the FFT leaves it: rows of ``n_ifft`` lags, of
        which the first ``n_lags`` are the correlation (the rest wraps around), C-contiguous;
        the FFTs on ``workers`` threads."""
        from echoloc.tof import _echoes_kernels as kernels  # numba: imported (and compiled) on first use

        frames = np.asarray(frames)
        rows = _float_rows(frames)
        correlation = kernels.correlate_rows(rows, self.n_fft, self.n_ifft, self._spectrum_single, workers)
        return np.asarray(correlation).reshape(*frames.shape[:-1], self.n_ifft)


MATCHED_DECIMATION = 2
"""The decimation of the `matched` estimator's correlation (:class:`MatchedFilter`): its
even lags carry all of the analytic correlation, and half the lags halve the inverse FFT
and every per-lag step of detection."""


def noise_power(values: NDArray[Any]) -> float:
    """Mean power of circular Gaussian noise from its median: ``median(|x|^2) / ln 2``."""
    power = float(np.median(np.abs(values) ** 2)) / _LN2 if np.size(values) else 0.0
    return power if power > 0 else float(np.finfo(float).tiny)


def _window(values: NDArray[np.complex128], centre: int, half: int) -> tuple[NDArray[np.complex128], int]:
    """``values[centre-half : centre+half+1]`` zero-padded at the edges, and its start."""
    start = centre - half
    out = np.zeros(2 * half + 1, dtype=complex)
    lo, hi = max(start, 0), min(centre + half + 1, len(values))
    out[lo - start : hi - start] = values[lo:hi]
    return out, start


def _subtract(
    values: NDArray[np.complex128], shape: NDArray[np.complex128], start: int, scale: complex
) -> None:
    lo, hi = max(start, 0), min(start + len(shape), len(values))
    values[lo:hi] -= scale * shape[lo - start : hi - start]


@dataclass
class _Component:
    tof_samples: float
    amplitude: complex


class _Clean:
    """CLEAN extraction and refinement on one channel's analytic correlation.

    With ``compiled`` (the default) :meth:`run` is one compiled call
    (:func:`echoloc.tof._echoes_kernels.clean_run`: noise power, extraction, merging, joint fits,
    model choice); without, it runs the Python statements below (their fits of candidate
    models call the compiled Levenberg-Marquardt, :func:`echoloc.tof._echoes_kernels.joint_fit`),
    which the tests hold the compiled loops to. The other methods are the statement only.
    """

    def __init__(self, mf: MatchedFilter, options: EchoOptions, compiled: bool = True):
        self.mf = mf
        self.options = options
        self.compiled = compiled
        self.table = mf.acf_table
        self.half = mf.half_width
        self.residue = mf.residue_lags
        self.fit_half = max(1, round(mf.mainlobe_lags / 2))
        self.merge_samples = mf.mainlobe_lags / 4
        self.cluster_samples = 2 * mf.mainlobe_lags

    def _fit(self, values: NDArray[np.complex128], peak: int) -> _Component:
        """Delay and complex amplitude of one echo whose envelope peaks at index ``peak``.

        Coarse delay: parabola through the envelope at the peak and its neighbours.
        Fine delay: the carrier phase, ``arg c[m] = rate (m - tof) + arg(a)``, at the
        peak and its neighbours (weighted by power). A real echo has arg(a) = 0 or pi,
        so each sample gives the delay modulo half a carrier period; the candidate
        nearest the coarse delay is taken. Amplitude: least squares of the template's
        autocorrelation at that delay over the main lobe.
        """
        n = len(values)
        lo, hi = max(peak - 1, 0), min(peak + 2, n)
        samples = [complex(v) for v in values[lo:hi]]
        env = [abs(v) for v in samples]
        offset = 0.0
        if hi - lo == 3:
            a, b, c = env
            denominator = a - 2 * b + c
            if denominator < 0:
                offset = min(max(0.5 * (a - c) / denominator, -0.5), 0.5)
        coarse = peak + offset
        rate = self.mf.phase_rate_rad_per_lag
        period = math.pi / rate  # half a carrier cycle, in samples
        weighted = total = 0.0
        for m, (value, magnitude) in enumerate(zip(samples, env, strict=True), start=lo):
            estimate = m - cmath.phase(value) / rate
            estimate += period * round((coarse - estimate) / period)
            weighted += magnitude**2 * estimate
            total += magnitude**2
        tof = weighted / total if total > 0 else coarse
        if abs(tof - coarse) > 1.5:
            tof = coarse
        shape, start = self._shape(tof)
        centre = round(tof)
        segment, seg_start = _window(values, centre, self.fit_half)
        model = shape[seg_start - start : seg_start - start + len(segment)]
        amplitude = complex(np.vdot(model, segment) / np.vdot(model, model).real)
        return _Component(tof, amplitude)

    def _shape(self, tof_samples: float) -> tuple[NDArray[np.complex128], int]:
        """Template autocorrelation for an echo at ``tof_samples``, and its first index.

        Linear interpolation between the table's sub-sample shifts, so the shape
        moves smoothly with the delay (the joint fit differentiates it).
        """
        shape, _, start = self._shape_and_slope(tof_samples)
        return shape, start

    def _shape_and_slope(
        self, tof_samples: float
    ) -> tuple[NDArray[np.complex128], NDArray[np.complex128], int]:
        """The interpolated shape, its derivative in the delay (per sample), and its first index."""
        u = self.mf.oversample
        position = tof_samples * u
        g0 = math.floor(position)
        weight = position - g0
        base0, j0 = divmod(g0, u)
        base1, j1 = divmod(g0 + 1, u)
        row0 = self.table[j0]
        row1 = self.table[j1]
        if base1 != base0:
            # The next shift belongs to the next whole sample: align it one lag later.
            shifted = np.zeros_like(row0)
            shifted[1:] = row1[:-1]
            row1 = shifted
        return (1 - weight) * row0 + weight * row1, (row1 - row0) * u, base0 - self.half

    def _joint_fit(
        self, residual: NDArray[np.complex128], cluster: list[_Component], power: float
    ) -> list[_Component]:
        """Fit overlapping echoes together: least squares over every delay and (real) amplitude.

        Successive single fits can settle on a wrong split when main lobes overlap by
        more than half; the joint fit of the model ``sum_k a_k R(m - tau_k)`` to the
        data (the residual with the cluster put back) over the cluster's span does
        not. Components that drift within a quarter main lobe of each other, or fall
        below the detection threshold, are dropped and the rest fitted again.
        """
        for member in cluster:
            self._take_out(residual, member.tof_samples, -member.amplitude)
        threshold = 10 ** (self.options.threshold_db / 10) * power
        members = sorted(cluster, key=lambda c: c.tof_samples)
        for _ in range(len(cluster)):
            lo = max(math.floor(members[0].tof_samples) - self.fit_half, 0)
            hi = min(math.ceil(members[-1].tof_samples) + self.fit_half + 1, len(residual))
            tofs = np.array([m.tof_samples for m in members])
            amplitudes = self._fit_model(
                residual[lo:hi], lo, tofs, np.array([m.amplitude for m in members], dtype=complex)
            )
            if not (np.all(np.isfinite(tofs)) and np.all(np.abs(tofs - (lo + hi) / 2) < hi - lo)):
                # A fit that ran away from its window keeps what successive refinement found.
                break
            fitted = [_Component(float(t), complex(a.real)) for t, a in zip(tofs, amplitudes, strict=True)]
            fitted.sort(key=lambda c: c.tof_samples)
            kept = [c for c in fitted if abs(c.amplitude) ** 2 >= threshold and lo <= c.tof_samples < hi]
            pruned: list[_Component] = []
            for c in kept:
                if pruned and c.tof_samples - pruned[-1].tof_samples < self.merge_samples:
                    if abs(c.amplitude) > abs(pruned[-1].amplitude):
                        pruned[-1] = c
                    continue
                pruned.append(c)
            if len(pruned) == len(fitted) or not pruned:
                members = pruned
                break
            members = pruned
        for member in members:
            self._take_out(residual, member.tof_samples, member.amplitude)
        return members

    def _fit_model(
        self,
        values: NDArray[np.complex128],
        first: int,
        tofs: NDArray[np.float64],
        amplitudes: NDArray[np.complex128],
    ) -> NDArray[np.complex128]:
        """Least squares of ``sum_k a_k R(s - tau_k)`` to ``values`` (samples from ``first``):
        ``tofs`` in place, the (real) amplitudes returned.

        First with complex amplitudes: the cost is then smooth in the delays (the envelope),
        where with real amplitudes it has a minimum every half carrier cycle. Then with real
        amplitudes from there: the carrier phase pins the delays. The complex fit steps in the
        frame turning with the carrier and stops at 1e-3 samples or a 1 % gain.
        """
        from echoloc.tof import _echoes_kernels as kernels  # numba: imported (and compiled) on first use

        data = np.ascontiguousarray(np.stack([values.real, values.imag], axis=-1))
        args = (
            self.mf.acf_table,
            self.mf.oversample,
            self.mf.half_width,
            data,
            first,
            np.ones(len(values), bool),
        )
        rate = self.mf.phase_rate_rad_per_lag
        amplitudes = amplitudes.copy()
        # Every argument given: numba's dispatcher takes a slow path for omitted defaults.
        complex_stop = (_CLEAN_COMPLEX_ITERATIONS, True, rate, _CLEAN_COMPLEX_TOLERANCE, _CLEAN_COMPLEX_GAIN)
        kernels.joint_fit(*args, tofs, amplitudes, False, *complex_stop)
        amplitudes = np.where(amplitudes.real >= 0, np.abs(amplitudes), -np.abs(amplitudes)) + 0j
        kernels.joint_fit(*args, tofs, amplitudes, True, _CLEAN_REAL_ITERATIONS, True, 0.0, 1e-6, 0.0)
        return np.asarray(amplitudes)

    def _take_out(self, residual: NDArray[np.complex128], tof_samples: float, amplitude: complex) -> None:
        """Subtract an echo's correlation model ``amplitude R(m - tof)`` from ``residual``."""
        shape, start = self._shape(tof_samples)
        _subtract(residual, shape, start, amplitude)

    def _refit(self, residual: NDArray[np.complex128], component: _Component) -> None:
        """Put the component back into the residual, fit it again alone, take it out again."""
        shape, start = self._shape(component.tof_samples)
        _subtract(residual, shape, start, -component.amplitude)
        centre = round(component.tof_samples)
        lo = max(centre - self.fit_half, 0)
        hi = min(centre + self.fit_half + 1, len(residual))
        peak = lo + int(np.argmax(np.abs(residual[lo:hi]))) if hi > lo else centre
        refined = self._fit(residual, min(max(peak, 0), len(residual) - 1))
        component.tof_samples, component.amplitude = refined.tof_samples, refined.amplitude
        shape, start = self._shape(component.tof_samples)
        _subtract(residual, shape, start, component.amplitude)

    def _merge_close(
        self, residual: NDArray[np.complex128], components: list[_Component]
    ) -> list[_Component]:
        """Fuse components closer than a quarter main lobe: one echo that CLEAN split."""
        components = sorted(components, key=lambda c: c.tof_samples)
        merged: list[_Component] = []
        for component in components:
            if merged and component.tof_samples - merged[-1].tof_samples < self.merge_samples:
                previous = merged[-1]
                # Undo the split: put both back, fit one echo at the stronger peak.
                for part in (previous, component):
                    self._take_out(residual, part.tof_samples, -part.amplitude)
                if abs(component.amplitude) > abs(previous.amplitude):
                    previous.tof_samples = component.tof_samples
                previous.amplitude = 0j
                self._refit(residual, previous)
                continue
            merged.append(component)
        return merged

    def _extract(self, residual: NDArray[np.complex128], components: list[_Component], power: float) -> int:
        """Take echoes out of ``residual`` strongest first while above the threshold; how many.

        The strongest sample is looked for among those the dynamic range leaves
        (:meth:`_below_floor`): near a strong echo what its subtraction left is not searched,
        elsewhere everything above the threshold is, however weak beside the frame's strongest.
        """
        threshold = 10 ** (self.options.threshold_db / 10)
        floor = 10 ** (-self.options.dynamic_range_db / 20)
        first = self.mf.first_lag(self.options.blanking_s)
        strongest = max((abs(c.amplitude) for c in components), default=0.0)
        added = 0
        while len(components) < self.options.max_echoes:
            magnitude = np.abs(residual)
            # Nothing is looked for inside the blanking interval (ring-down, direct coupling).
            magnitude[:first] = 0.0
            magnitude[self._below_floor(residual, components, floor)] = 0.0
            peak = int(np.argmax(magnitude))
            height = float(magnitude[peak])
            if height**2 < threshold * power or height < _PRECISION_AMPLITUDE * strongest:
                break
            component = self._fit(residual, peak)
            shape, start = self._shape(component.tof_samples)
            _subtract(residual, shape, start, component.amplitude)
            cluster = [
                c for c in components if abs(c.tof_samples - component.tof_samples) < self.cluster_samples
            ]
            components.append(component)
            added += 1
            if cluster:
                self._refit_together([*cluster, component], residual)
            strongest = max(strongest, abs(component.amplitude))
        return added

    def _below_floor(
        self, residual: NDArray[np.complex128], components: list[_Component], floor: float
    ) -> NDArray[np.bool_]:
        """The samples of ``residual`` that the dynamic range leaves out of the search: those
        whose power ``re^2 + im^2`` is below ``(floor |a|)^2`` of a component within
        :attr:`MatchedFilter.residue_lags` of them (``|s - tof| <= residue_lags``).

        What imperfect subtraction leaves of an echo (a template that differs from the echo, a
        delay or amplitude slightly off), and its sidelobes, lie within that reach and scale
        with the echo; farther out the echo leaves nothing, so nothing is masked there.
        """
        n = len(residual)
        level = np.zeros(n)
        for c in components:
            if not math.isfinite(c.tof_samples):
                continue
            lo = max(math.ceil(c.tof_samples - self.residue), 0)
            hi = min(math.floor(c.tof_samples + self.residue) + 1, n)
            if hi > lo:
                amplitude = floor * abs(c.amplitude)
                np.fmax(level[lo:hi], amplitude * amplitude, out=level[lo:hi])
        powers = residual.real**2 + residual.imag**2
        return np.asarray(powers < level)

    def _refit_together(self, cluster: list[_Component], residual: NDArray[np.complex128]) -> None:
        """Successive refinement: fit each member with the others removed, a few passes."""
        for _ in range(self.options.refine_passes):
            for member in cluster:
                self._refit(residual, member)

    def _fit_cluster(
        self, residual: NDArray[np.complex128], cluster: list[_Component], power: float
    ) -> list[_Component]:
        """A joint fit of a cluster whose main lobes overlap by more than half; else as it is."""
        delays = sorted(c.tof_samples for c in cluster)
        if min(np.diff(delays)) < self.mf.mainlobe_lags:
            return self._joint_fit(residual, cluster, power)
        return cluster

    def run(self, correlation: NDArray[np.complex128]) -> tuple[list[_Component], float]:
        """Extract echoes strongest first, then fit overlapping ones together.

        Each new echo is fitted alone (exact when isolated). When it lies within two
        main lobes of earlier ones, the cluster is fitted again by successive
        refinement. Clusters whose members are closer than one main lobe are then
        fitted jointly (:meth:`_joint_fit`).
        """
        if self.compiled:
            return self._run_compiled(correlation)
        residual = correlation.copy()
        components: list[_Component] = []
        power = self._noise_power(residual)
        self._extract(residual, components, power)
        # The first noise estimate includes the echoes' sidelobes; redo it on the residual.
        power = self._noise_power(residual)
        self._extract(residual, components, power)
        merged: list[_Component] = []
        for group in _clusters(self._merge_close(residual, components), self.cluster_samples):
            fitted = self._fit_cluster(residual, group, power) if len(group) > 1 else group
            merged.extend(self._choose_order(residual, fitted, power))
        return merged, power

    def run_rows(
        self, correlations: NDArray[np.complex128], threads: int = 1
    ) -> list[tuple[list[_Component], float]]:
        """:meth:`run` on every row of ``correlations`` (n_rows, n_samples); compiled, with
        ``threads`` above 1, the rows are shared out among that many threads
        (:func:`echoloc.tof._echoes_kernels.clean_run_rows`, the same answers)."""
        parts = _kernel_threads(threads, len(correlations)) if self.compiled else 1
        if parts == 1:
            return [self.run(row) for row in correlations]
        from echoloc.tof import _echoes_kernels as kernels

        n_rows = len(correlations)
        room = 2 * max(self.options.max_echoes, 1)  # a split adds at most one echo per group
        tofs = np.zeros((n_rows, room))
        amplitudes = np.zeros((n_rows, room), dtype=complex)
        power = np.zeros(n_rows)
        count = np.zeros(n_rows, dtype=np.int64)
        run_kernel(
            parts,
            kernels.clean_run_rows,
            *self._compiled_arguments(),
            np.array(correlations, dtype=complex),  # the residuals, taken apart in place
            tofs,
            amplitudes,
            power,
            count,
        )
        components = [
            [_Component(float(tofs[r, i]), complex(amplitudes[r, i])) for i in range(count[r])]
            for r in range(n_rows)
        ]
        return list(zip(components, power.tolist(), strict=True))

    def _compiled_arguments(self) -> tuple[Any, ...]:
        """The arguments of :func:`echoloc.tof._echoes_kernels.clean_run` before the channel's own."""
        options = self.options
        return (
            self.table,
            self.mf.oversample,
            self.half,
            self.mf.phase_rate_rad_per_lag,
            self.fit_half,
            self.mf.mainlobe_lags,
            self.mf.residue_lags,
            self.merge_samples,
            self.cluster_samples,
            self.mf.acf_energy,
            10 ** (options.threshold_db / 10),
            10 ** (-options.dynamic_range_db / 20),
            self.mf.first_lag(options.blanking_s),
            options.max_echoes,
            options.refine_passes,
            _CLEAN_COMPLEX_ITERATIONS,
            _CLEAN_REAL_ITERATIONS,
            _CLEAN_COMPLEX_TOLERANCE,
            _CLEAN_COMPLEX_GAIN,
        )

    def _run_compiled(self, correlation: NDArray[np.complex128]) -> tuple[list[_Component], float]:
        """:meth:`run` in one compiled call (:func:`echoloc.tof._echoes_kernels.clean_run`)."""
        from echoloc.tof import _echoes_kernels as kernels

        tofs = np.zeros(2 * max(self.options.max_echoes, 1))  # a split adds at most one echo per group
        amplitudes = np.zeros(len(tofs), dtype=complex)
        power = np.zeros(1)
        run: Callable[..., int] = kernels.clean_run
        count = run(
            *self._compiled_arguments(),
            np.array(correlation, dtype=complex),  # the residual, taken apart in place
            tofs,
            amplitudes,
            power,
        )
        return [_Component(float(tofs[i]), complex(amplitudes[i])) for i in range(count)], float(power[0])

    def _noise_power(self, residual: NDArray[np.complex128]) -> float:
        """:func:`noise_power`, the power of each sample as ``re^2 + im^2`` (as the batch path
        takes it: the magnitude's ``hypot`` slowed CLEAN's compiled run)."""
        powers = residual.real**2 + residual.imag**2
        power = float(np.median(powers)) / _LN2 if len(powers) else 0.0
        return power if power > 0 else float(np.finfo(float).tiny)

    def _window_cost(self, residual: NDArray[np.complex128], lo: int, hi: int) -> float:
        return float(np.sum(np.abs(residual[lo:hi]) ** 2))

    def _choose_order(
        self, residual: NDArray[np.complex128], group: list[_Component], power: float
    ) -> list[_Component]:
        """Whether a stretch CLEAN fitted holds one echo more than it found.

        Joint fits settle on the echoes they start from: two equal echoes half a main
        lobe apart can come out as one at their midpoint, or as one plus a stray.
        Where the fitted model leaves more than noise around its echoes, models with
        one echo split in two (a quarter and half a main lobe either side) are fitted
        jointly too. A split replaces CLEAN's model only when it keeps both parts
        (neither below a quarter of the other: a faint partner fits the main echo's
        imperfections) and lowers the residual by more than a penalty per echo, half
        the energy an echo at the detection threshold puts into its main lobe.
        """
        if not group:
            return group
        if len(group) > 1:
            return self._choose_overlapping(residual, group, power)
        tofs = [c.tof_samples for c in group]
        span = math.ceil(self.mf.mainlobe_lags)
        lo = max(math.floor(min(tofs)) - span, 0)
        hi = min(math.ceil(max(tofs)) + span + 1, len(residual))
        base_cost = self._window_cost(residual, lo, hi)
        # Noise alone leaves about `power` per sample: a model that explains its stretch
        # needs no second look.
        echo_energy = abs(group[0].amplitude) ** 2 * self.mf.acf_energy
        if base_cost < 3.0 * power * (hi - lo) or base_cost < 0.003 * echo_energy:
            # Nothing but noise left, or less than 0.3 % of the echo's energy: a strong echo's
            # tiny misfit, not a second echo merged into it.
            return group
        candidates: list[list[_Component]] = []
        quarter = self.mf.mainlobe_lags / 4
        for i, member in enumerate(group):
            for offset in (quarter, 2 * quarter):
                half = _Component(member.tof_samples, member.amplitude / 2)
                split = [
                    _Component(member.tof_samples - offset, half.amplitude),
                    _Component(member.tof_samples + offset, half.amplitude),
                ]
                candidates.append([*group[:i], *split, *group[i + 1 :]])

        def keep(fitted: list[_Component]) -> bool:
            # A split that fell back together leaves CLEAN's model (a re-fit of echoes too
            # close to part would only move them to their centroid); one that leaves a faint
            # partner (below a quarter of the other) is fitting the main echo's
            # imperfections (a half-cycle sidelobe of the fit), not a second echo.
            magnitudes = [abs(c.amplitude) for c in fitted]
            return len(fitted) > len(group) and min(magnitudes) >= 0.25 * max(magnitudes)

        return self._try_models(residual, group, candidates, power, keep)

    def _plausible(self, components: list[_Component]) -> bool:
        """Whether echoes closer than a main lobe could be two reflectors rather than one echo's misfit.

        Two echoes within a main lobe of each other with opposite signs cancel each
        other's carrier: such a pair fits the distortion of one echo (or a pair fitted
        half a carrier cycle off), not two rigid reflectors, whose echoes share the sign.
        Nor does a partner below a quarter of its neighbour (the split test's rule).
        """
        ordered = sorted(components, key=lambda c: c.tof_samples)
        for first, second in itertools.pairwise(ordered):
            if second.tof_samples - first.tof_samples >= self.mf.mainlobe_lags:
                continue
            a, b = first.amplitude.real, second.amplitude.real
            if a * b < 0 or min(abs(a), abs(b)) < 0.25 * max(abs(a), abs(b)):
                return False
        return True

    def _try_models(
        self,
        residual: NDArray[np.complex128],
        group: list[_Component],
        candidates: list[list[_Component]],
        power: float,
        keep: Callable[[list[_Component]], bool],
    ) -> list[_Component]:
        """The candidate model (jointly fitted from its starting echoes) of lowest penalised cost.

        Every candidate is fitted over the group's stretch (a main lobe beyond its first
        and last echo) with the group put back, all at once (:func:`_joint_fit_batch`:
        complex amplitudes, then real ones). A fit with an echo below the detection
        threshold, two echoes within a quarter main lobe, an echo outside the stretch, or
        that ``keep`` refuses, is dropped. Cost: the residual's energy over the stretch
        plus a penalty per echo, half the energy an echo at the detection threshold puts
        into its main lobe; ``group`` (already fitted) competes too. The winner replaces
        the group in ``residual``.
        """
        tofs = [c.tof_samples for c in group]
        span = math.ceil(self.mf.mainlobe_lags)
        lo = max(math.floor(min(tofs)) - span, 0)
        hi = min(math.ceil(max(tofs)) + span + 1, len(residual))
        if not candidates or hi - lo < 2:
            return group
        threshold = 10 ** (self.options.threshold_db / 10) * power
        penalty = 0.5 * threshold * self.mf.acf_energy
        restored = residual.copy()
        for member in group:  # the data: the residual with the group put back
            self._take_out(restored, member.tof_samples, -member.amplitude)
        k = max(len(c) for c in candidates)
        n_rows = len(candidates)
        start_tof = np.full((n_rows, k), tofs[0])
        start_amplitude = np.zeros((n_rows, k), dtype=complex)
        active = np.zeros((n_rows, k), dtype=bool)
        for row, candidate in enumerate(candidates):
            for slot, member in enumerate(candidate):
                start_tof[row, slot] = member.tof_samples
                start_amplitude[row, slot] = member.amplitude
                active[row, slot] = True
        # Each candidate is fitted as :meth:`_joint_fit` fits a cluster, over its own span (half
        # a main lobe beyond its first and last echo), and scored over the group's stretch.
        fit_tof = start_tof.copy()
        fit_amplitude = start_amplitude.copy()
        cost = np.full(n_rows, np.inf)
        stretch = np.arange(lo, hi)
        for row in range(n_rows):
            members = np.flatnonzero(active[row])
            if len(members) == 0:
                continue
            t, a = start_tof[row, members].copy(), start_amplitude[row, members].copy()
            first = min(max(math.floor(t.min()) - self.fit_half, lo), hi - 2)
            last = max(min(math.ceil(t.max()) + self.fit_half + 1, hi), first + 2)
            a = self._fit_model(restored[first:last], first, t, a)
            model = np.sum(
                a[:, None] * _shape_values(self.mf, t, np.broadcast_to(stretch, (len(t), hi - lo))), axis=0
            )
            cost[row] = float(np.sum(np.abs(restored[lo:hi] - model) ** 2))
            fit_tof[row, members], fit_amplitude[row, members] = t, a
        best, best_score = group, self._window_cost(residual, lo, hi) + penalty * len(group)
        if not self._plausible(group):
            best_score = math.inf  # any plausible candidate replaces it
        scores = cost + penalty * np.sum(active, axis=1)
        for row in range(n_rows):
            if not scores[row] < best_score - 1e-12:
                # It could not replace the best so far, valid or not (nor can a NaN or
                # infinite cost): the checks below are for the rows that would.
                continue
            fitted = sorted(
                (
                    _Component(float(fit_tof[row, slot]), complex(fit_amplitude[row, slot].real))
                    for slot in np.flatnonzero(active[row])
                ),
                key=lambda c: c.tof_samples,
            )
            delays = [c.tof_samples for c in fitted]
            if (
                not np.isfinite(cost[row])
                or any(abs(c.amplitude) ** 2 < threshold for c in fitted)
                or any(not lo <= t < hi for t in delays)
                or (len(delays) > 1 and min(np.diff(delays)) < self.merge_samples)
                or not keep(fitted)
                or not self._plausible(fitted)
            ):
                continue
            best, best_score = fitted, float(scores[row])
        if best is not group:
            residual[:] = restored
            for member in best:
                self._take_out(residual, member.tof_samples, member.amplitude)
        return best

    def _choose_overlapping(
        self, residual: NDArray[np.complex128], group: list[_Component], power: float
    ) -> list[_Component]:
        """Other readings of echoes fitted together whose main lobes overlap by more than half.

        The joint fit with real amplitudes has a local minimum every half carrier cycle
        (an echo half a cycle off with its sign flipped matches the carrier), and where
        two echoes merge into one envelope peak a third echo can make up for a pair
        fitted on the wrong half-cycle. So each echo is also started half a cycle
        earlier and later with its sign flipped, and each is left out in turn; the
        model of lowest penalised cost (:meth:`_try_models`) wins, and the search is
        repeated from it while it improves (at most ``len(group)`` rounds).
        """
        delays = sorted(c.tof_samples for c in group)
        if len(group) < 2 or min(np.diff(delays)) >= self.mf.mainlobe_lags:
            return group
        period = math.pi / self.mf.phase_rate_rad_per_lag  # half a carrier cycle, samples
        # The whole stretch read afresh as two echoes either side of its centroid (a quarter
        # and half a main lobe apart), as the split test reads a single echo.
        weights = np.array([abs(c.amplitude) ** 2 for c in group])
        centroid = float(np.dot(weights, _delays(group)) / max(float(np.sum(weights)), 1e-300))
        half_amplitude = complex(sum(abs(c.amplitude) for c in group) / 2)
        fresh = [
            [_Component(centroid - offset, half_amplitude), _Component(centroid + offset, half_amplitude)]
            for offset in (self.mf.mainlobe_lags / 4, self.mf.mainlobe_lags / 2)
        ]
        for round_ in range(len(group)):
            candidates: list[list[_Component]] = fresh if round_ == 0 else []
            for i, member in enumerate(group):
                for step in (-period, period):
                    moved = _Component(member.tof_samples + step, -member.amplitude)
                    candidates.append([*group[:i], moved, *group[i + 1 :]])
                rest = [*group[:i], *group[i + 1 :]]
                if rest:
                    candidates.append(rest)
                if len(rest) > 1:
                    # Left out, with another moved by half a cycle: a stray and a slip together.
                    for j, other in enumerate(rest):
                        for step in (-period, period):
                            moved = _Component(other.tof_samples + step, -other.amplitude)
                            candidates.append([*rest[:j], moved, *rest[j + 1 :]])
            best = self._try_models(residual, group, candidates, power, keep=lambda fitted: True)
            if best is group:
                break
            group = best
        return group


def _delays(components: list[_Component]) -> NDArray[np.float64]:
    """The components' delays, samples."""
    return np.array([c.tof_samples for c in components])


def _clusters(components: list[_Component], gap_samples: float) -> list[list[_Component]]:
    """Group components whose delays chain together closer than ``gap_samples``."""
    groups: list[list[_Component]] = []
    for component in sorted(components, key=lambda c: c.tof_samples):
        if groups and component.tof_samples - groups[-1][-1].tof_samples < gap_samples:
            groups[-1].append(component)
        else:
            groups.append([component])
    return groups


def matched_filter_echoes(
    frames: NDArray[np.floating], mf: MatchedFilter, options: EchoOptions
) -> list[ChannelEchoes]:
    """Matched-filter echoes of one frame (n_rx, n_samples)."""
    return matched_filter_batch(np.asarray(frames)[None], mf, options)[0]


def matched_filter_batch(
    frames: NDArray[np.floating], mf: MatchedFilter, options: EchoOptions
) -> list[list[ChannelEchoes]]:
    """Matched-filter echoes of many frames (n_frames, n_rx, n_samples) at once.

    The correlation of every channel is computed at once in single precision; then
    every channel goes through the batch path (:func:`_isolated_echoes`, run with the
    correlation as one compiled call, :func:`_correlated_channels`: :func:`_compiled_batch`
    then :func:`_finish_batch`), which fits
    isolated echoes as CLEAN does and clusters of echoes within two main lobes jointly. An
    echo whose model leaves its two main lobes unexplained is split there into the best
    pair (:func:`echoloc.tof._echoes_kernels._split_echo`: two echoes whose main lobes merged,
    or one echo when they lie closer than CLEAN resolves). A channel whose echoes it still
    cannot vouch for (echoes within a quarter main lobe, anything left in the correlation
    that its echoes do not explain) is handed to CLEAN (:class:`_Clean`) on its
    double-precision correlation.
    With ``options.workers`` above 1, the channels of both stages are spread over threads.
    """
    frames = np.asarray(frames)
    return with_clean(frames, _correlated_channels(frames, mf, options, options.threads), mf, options)


def with_clean(
    frames: NDArray[Any], channels: list[ChannelEchoes | None], mf: MatchedFilter, options: EchoOptions
) -> list[list[ChannelEchoes]]:
    """The echoes of ``frames`` (n_frames, n_rx, n_samples) by frame: ``channels`` (every
    channel's, frame after frame), CLEAN's (:class:`_Clean`) where it holds None."""
    n_frames, n_rx, _ = frames.shape
    threads = options.threads
    hard = [index for index, found in enumerate(channels) if found is None]
    if hard:
        clean = _Clean(mf, options)
        # The double-precision correlation of every hard channel in one call (the same values
        # as one call a channel, in less time).
        exact = mf.correlate(frames.reshape(n_frames * n_rx, -1)[hard], threads)
        for index, (components, power) in zip(hard, clean.run_rows(exact, threads), strict=True):
            tof = np.array([c.tof_samples for c in components])
            amplitude = np.array([abs(c.amplitude) for c in components])
            snr_db = 10 * np.log10(np.maximum(amplitude**2, 1e-300) / power)
            tof_s = tof / mf.lag_rate_hz + mf.arrival_s
            channels[index] = finish_channel(tof_s, amplitude, snr_db, options, mf.support_s)
    done = [c for c in channels if c is not None]
    return [done[i * n_rx : (i + 1) * n_rx] for i in range(n_frames)]


_FFT_ROWS_PER_WORKER = 32
"""scipy.fft's threads pay off from about this many rows a thread. On fewer they cost more
than they save: on two cores, correlating 2 or 4 rows of 2400 samples was slower with
``workers=-1`` than with one thread."""


def fft_workers(threads: int, rows: int) -> int:
    """Threads, at most ``threads``, for scipy.fft over ``rows`` rows (:data:`_FFT_ROWS_PER_WORKER`)."""
    return max(1, min(threads, rows // _FFT_ROWS_PER_WORKER))


_PARALLEL_LAUNCH = threading.Lock()
"""Held while a compiled kernel runs its loops on several threads (:func:`run_kernel`)."""


def run_kernel(parts: int, kernel: Callable[..., Any], *arguments: Any) -> Any:
    """``kernel(*arguments)``; when it runs ``parts`` > 1 threads, one such call at a time.

    Where neither OpenMP nor TBB is installed, numba runs parallel loops on its workqueue
    threading layer, which terminates the process when two Python threads start parallel
    loops at once (two stream processors with ``workers`` > 1 in two threads did). The calls
    on one thread (every stream frame on one core) take no lock."""
    if parts <= 1:
        return kernel(*arguments)
    with _PARALLEL_LAUNCH:
        return kernel(*arguments)


def _kernel_threads(threads: int, tasks: int) -> int:
    """Threads for a compiled parallel loop over ``tasks``, set as numba's count for the call."""
    from echoloc._jit import set_threads

    return set_threads(threads, tasks)


_FastResult = tuple[NDArray[np.float64], NDArray[np.float64], float]


def _shape_values(
    mf: MatchedFilter, tof_samples: NDArray[np.float64], samples: NDArray[np.int64]
) -> NDArray[np.complex128]:
    """The template's autocorrelation ``R(s - tof)`` at integer samples ``s`` (..., w) for delays (...,).

    Linear interpolation between the sub-sample table's rows, as :meth:`_Clean._shape`.
    """
    return _shape_and_slope_values(mf, tof_samples, samples, slope=False)[0]


def _shape_and_slope_values(
    mf: MatchedFilter, tof_samples: NDArray[np.float64], samples: NDArray[np.int64], slope: bool = True
) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
    """``R(s - tof)`` and its derivative in ``tof`` (per sample), as :meth:`_Clean._shape_and_slope`.

    Without ``slope`` the second array is empty.
    """
    u, half, table = mf.oversample, mf.half_width, mf.acf_table
    position = tof_samples * u
    grid = np.floor(position).astype(np.int64)
    weight = (position - grid)[..., None]
    base0, row0 = np.divmod(grid, u)
    base1, row1 = np.divmod(grid + 1, u)
    width = 2 * half + 1
    lag0 = samples - base0[..., None] + half
    lag1 = samples - base1[..., None] + half
    v0 = table[row0[..., None], np.clip(lag0, 0, width - 1)]
    v1 = table[row1[..., None], np.clip(lag1, 0, width - 1)]
    v0[(lag0 < 0) | (lag0 >= width)] = 0
    v1[(lag1 < 0) | (lag1 >= width)] = 0
    values = v0 + weight * (v1 - v0)
    return values, ((v1 - v0) * u if slope else np.zeros(0, dtype=complex))


def _model_at(
    mf: MatchedFilter,
    echo_ch: NDArray[np.int64],
    echo_tof: NDArray[np.float64],
    echo_amplitude: NDArray[np.complex128],
    probe_ch: NDArray[np.int64],
    probe: NDArray[np.int64],
    exclude: NDArray[np.int64] | None = None,
    echo_group: NDArray[np.int64] | None = None,
) -> NDArray[np.complex128]:
    """Sum of the echoes' correlation model ``a R(s - tof)`` at probe samples (n_probes, w).

    Each probe row sums the echoes of its own channel within the template's reach,
    except echo ``exclude[row]`` (its own echo, when fitting it; with ``echo_group``, every
    echo of group ``exclude[row]``: its own cluster). Echoes are grouped
    by channel through a sort, so the work is the probes times their channel's echoes.
    """
    model = np.zeros(probe.shape, dtype=complex)
    if len(echo_ch) == 0 or len(probe_ch) == 0:
        return model
    order = np.argsort(echo_ch, kind="stable")
    sorted_ch = echo_ch[order]
    start = np.searchsorted(sorted_ch, probe_ch, side="left")
    count = np.searchsorted(sorted_ch, probe_ch, side="right") - start
    centre = probe[:, probe.shape[1] // 2]
    reach = mf.half_width + probe.shape[1] // 2 + 1
    for slot in range(int(count.max(initial=0))):
        rows = np.flatnonzero(count > slot)
        echo = order[start[rows] + slot]
        keep = np.abs(centre[rows] - echo_tof[echo]) <= reach
        if exclude is not None:
            keep &= (echo if echo_group is None else echo_group[echo]) != exclude[rows]
        rows, echo = rows[keep], echo[keep]
        model[rows] += echo_amplitude[echo, None] * _shape_values(mf, echo_tof[echo], probe[rows])
    return model


def _joint_fit_batch(
    mf: MatchedFilter,
    data: NDArray[np.complex128],
    samples: NDArray[np.int64],
    valid: NDArray[np.bool_],
    tof: NDArray[np.float64],
    amplitude: NDArray[np.complex128],
    active: NDArray[np.bool_],
    real: bool,
    iterations: int,
) -> tuple[NDArray[np.float64], NDArray[np.complex128], NDArray[np.float64]]:
    """Least squares of ``sum_k a_k R(s - tau_k)`` to ``data`` (B, w) for B clusters at once.

    Levenberg-Marquardt on every row together (each row keeps its own damping, a step is
    taken only where it lowers that row's cost), as :meth:`_Clean._joint_fit` fits one
    cluster: complex amplitudes (smooth in the delays) or real ones (the carrier pins the
    delays). ``tof``/``amplitude``/``active`` are (B, K); samples outside ``valid`` and
    inactive members do not count. Returns the delays, amplitudes and each row's cost.
    """
    n_rows, k = tof.shape
    weight = valid[:, None, :] & active[:, :, None]

    def evaluate(
        tof: NDArray[np.float64], amplitude: NDArray[np.complex128]
    ) -> tuple[NDArray[np.complex128], NDArray[np.complex128], NDArray[np.complex128], NDArray[np.float64]]:
        shapes, slopes = _shape_and_slope_values(mf, tof, samples[:, None, :])
        shapes = np.where(weight, shapes, 0)
        slopes = np.where(weight, slopes, 0)
        residual = np.where(valid, data - np.einsum("bk,bkw->bw", amplitude, shapes), 0)
        return shapes, slopes, residual, np.sum(residual.real**2 + residual.imag**2, axis=1)

    shapes, slopes, residual, cost = evaluate(tof, amplitude)
    damping = np.full(n_rows, 1e-3)
    eye = np.eye(k * (2 if real else 3))
    for _ in range(iterations):
        columns = [amplitude[..., None] * slopes, shapes] + ([] if real else [1j * shapes])
        jac = np.concatenate(columns, axis=1)  # (B, P, w): d model / d parameter
        normal = np.real(np.conj(jac) @ np.swapaxes(jac, 1, 2))
        gradient = np.real(np.conj(jac) @ residual[..., None])[..., 0]
        diagonal = np.diagonal(normal, axis1=1, axis2=2)
        # An inactive member's parameters have zero columns: hold them with a unit diagonal.
        normal = normal + eye * (damping[:, None] * diagonal + (diagonal == 0))[:, None, :]
        step = np.linalg.solve(normal, gradient[..., None])[..., 0]
        new_tof = tof + np.clip(step[:, :k], -2.0, 2.0)
        new_amplitude = amplitude + step[:, k : 2 * k] + (0 if real else 1j * step[:, 2 * k :])
        trial = evaluate(new_tof, new_amplitude)
        better = trial[3] < cost
        tof = np.where(better[:, None], new_tof, tof)
        amplitude = np.where(better[:, None], new_amplitude, amplitude)
        shapes = np.where(better[:, None, None], trial[0], shapes)
        slopes = np.where(better[:, None, None], trial[1], slopes)
        residual = np.where(better[:, None], trial[2], residual)
        cost = np.where(better, trial[3], cost)
        damping = np.where(better, damping / 4, damping * 8)
    return tof, amplitude, cost


def _fit_peaks(
    mf: MatchedFilter,
    values: NDArray[np.complex128],
    neighbours: NDArray[np.int64],
    window_values: NDArray[np.complex128],
    window: NDArray[np.int64],
) -> tuple[NDArray[np.float64], NDArray[np.complex128]]:
    """Delays and complex amplitudes of isolated echoes, as :meth:`_Clean._fit` fits one.

    ``values`` are the correlation at each peak and its two neighbours (samples
    ``neighbours``), ``window_values`` over ``window`` (samples around the peak): the
    envelope parabola gives the coarse delay, the power-weighted carrier phase the fine
    one (the half-cycle ambiguity resolved by the coarse delay), and least squares over
    the window the amplitude.
    """
    env = np.abs(values)
    a, b, c = env[:, 0], env[:, 1], env[:, 2]
    curvature = a - 2 * b + c
    concave = curvature < 0
    offset = np.where(concave, np.clip(0.5 * (a - c) / np.where(concave, curvature, -1.0), -0.5, 0.5), 0.0)
    coarse = neighbours[:, 1] + offset
    rate = mf.phase_rate_rad_per_lag
    period = math.pi / rate
    estimates = neighbours - np.angle(values) / rate
    estimates += period * np.round((coarse[:, None] - estimates) / period)
    weights = env**2
    tof = np.sum(weights * estimates, axis=1) / np.maximum(np.sum(weights, axis=1), 1e-300)
    tof = np.where(np.abs(tof - coarse) > 1.5, coarse, tof)
    model = _shape_values(mf, tof, window)
    amplitude = np.sum(np.conj(model) * window_values, axis=1) / np.maximum(
        np.sum(np.abs(model) ** 2, axis=1), 1e-300
    )
    return tof, amplitude


def _sidelobe_envelope(mf: MatchedFilter) -> NDArray[np.float64]:
    """Sidelobe envelope of the template: max |R| within a lag of each lag, over every sample
    between (1 within a lag of 0)."""
    envelope = np.abs(mf._autocorrelation_full)
    d = mf.decimation
    lags = np.arange(-mf.half_width, mf.half_width + 1)
    within = lags[:, None] * d + np.arange(-d, d + 1)
    dilated = envelope[within % mf.n_fft].max(axis=1)
    dilated[np.abs(lags) < 2] = 1.0
    return np.asarray(dilated)


_NOISE_STEP = 4
"""The compiled batch path takes the noise power from the median of the correlation every 4th
sample (every 2nd lag at decimation 2): the correlation is band-limited (its main lobe is 17
samples wide), so the other samples add little, and the median of 600 values costs a quarter
of 2400."""


def _compiled_echoes(
    correlation: NDArray[np.complexfloating[Any, Any]],
    mf: MatchedFilter,
    options: EchoOptions,
    noise_step: int = _NOISE_STEP,
    max_splits: int | None = None,
) -> list[_FastResult | None]:
    """:func:`_isolated_echoes` in compiled loops (:mod:`echoloc.tof._echoes_kernels`), channel by channel.

    The same candidates, fits and checks; only the noise power comes from every
    ``noise_step``-th sample (1: all of them, as :func:`_isolated_echoes`), and an echo the
    checks find unexplained is split in two, up to ``max_splits`` times a channel (None:
    :data:`_MAX_SPLITS`; 0: never, as :func:`_isolated_echoes`).
    """
    out = _compiled_batch(correlation, mf, options, noise_step, max_splits=max_splits)
    return [
        (out.tof[c, : out.count[c]].copy(), out.amplitude[c, : out.count[c]].copy(), float(out.power[c]))
        if out.ok[c]
        else None
        for c in range(len(out.count))
    ]


@dataclass(frozen=True, eq=False)
class _BatchOutput:
    """What the compiled batch path returns for every channel: echoes in the first ``count`` slots."""

    tof: NDArray[np.float64]  # samples (n_channels, slots)
    amplitude: NDArray[np.float64]  # magnitudes (n_channels, slots)
    count: NDArray[np.int64]
    power: NDArray[np.float64]  # noise power of each channel's correlation
    ok: NDArray[np.bool_]  # False: the channel goes to CLEAN


class BatchConstants(NamedTuple):
    """What :func:`echoloc.tof._echoes_kernels.batch_echoes` takes that stays the same from
    frame to frame (a named tuple: numba reads its fields by name, so none is taken by position)."""

    table: NDArray[np.complex128]  # the autocorrelation at sub-sample shifts (MatchedFilter.acf_table)
    oversample: int  # table rows per lag
    half_width: int  # lags each side of the table's centre
    phase_rate_rad_per_lag: float
    sidelobe_envelope: NDArray[np.float64]  # the template's sidelobes' reach, per lag
    mainlobe_lags: float
    acf_energy: float
    threshold_factor: float  # the detection threshold as a power ratio
    dynamic_range: float  # the dynamic range as a power ratio (< 1)
    first_lag: int  # the first lag past the blanking time
    max_candidates: int
    residue_lags: int
    max_joint: int  # most echoes in one joint fit
    complex_iterations: int
    real_iterations: int
    lone_iterations: int
    max_splits: int  # most splits of an unexplained echo, a channel
    noise_step: int  # lags between the noise estimate's samples


class FinishingConstants(NamedTuple):
    """What :func:`echoloc.tof._echoes_kernels.finish_channels` takes that stays the same from
    frame to frame: the lag rate, the arrival offset (s), the blanking (s), the threshold (dB),
    the floor as an amplitude ratio below the strongest echo and the template's support (s)."""

    lag_rate_hz: float
    arrival_s: float
    blanking_s: float
    threshold_db: float
    floor_ratio: float
    support_s: float


class EchoKernelArguments(NamedTuple):
    """What :func:`echoloc.tof._echoes_kernels.correlate_and_fit` takes, as one argument it reads
    by name: the rows of samples, the FFT sizes, the template's spectrum, the FFT's threads, the
    fits' parallel parts, the lags, the two bundles of constants, then the outputs it writes:
    ``out`` (3, rows, slots: delays s, amplitudes, SNRs dB), ``kept`` (their counts) and
    ``ok`` (False: the row is left to CLEAN)."""

    frames: NDArray[np.float64]
    n_fft: int
    n_ifft: int
    weights: NDArray[np.complex64]
    workers: int
    parts: int
    n_lags: int
    constants: BatchConstants
    finishing: FinishingConstants
    out: NDArray[np.float64]
    kept: NDArray[np.int64]
    ok: NDArray[np.bool_]


_KernelConstants = tuple[BatchConstants, FinishingConstants]


def _kernel_constants(
    mf: MatchedFilter, options: EchoOptions, noise_step: int, max_splits: int
) -> _KernelConstants:
    """The arguments of the compiled batch path that stay the same from frame to frame:
    :func:`echoloc.tof._echoes_kernels.batch_echoes`' from ``table`` to ``noise_step``, and
    :func:`echoloc.tof._echoes_kernels.finish_channels`' from ``lag_rate_hz`` to ``support_s``.
    Built once for each ``mf`` and set of options (:attr:`MatchedFilter.kernel_constants_memo`)."""
    key = (
        options.threshold_db,
        options.dynamic_range_db,
        options.blanking_s,
        options.max_echoes,
        noise_step,
        max_splits,
    )
    memo = mf.kernel_constants_memo
    found = memo.get(key)
    if found is None:
        batch = BatchConstants(
            mf.acf_table,
            mf.oversample,
            mf.half_width,
            mf.phase_rate_rad_per_lag,
            mf.sidelobe_envelope,
            mf.mainlobe_lags,
            mf.acf_energy,
            10 ** (options.threshold_db / 10),
            10 ** (-options.dynamic_range_db / 10),
            max(mf.first_lag(options.blanking_s), 1),
            4 * options.max_echoes,
            mf.residue_lags,
            _MAX_JOINT,
            _COMPLEX_ITERATIONS,
            _REAL_ITERATIONS,
            _LONE_ITERATIONS,
            max_splits,
            max(1, noise_step // mf.decimation),
        )
        finishing = FinishingConstants(
            mf.lag_rate_hz,
            mf.arrival_s,
            options.blanking_s,
            options.threshold_db,
            10 ** (-options.dynamic_range_db / 20),
            mf.support_s,
        )
        found = memo[key] = (batch, finishing)
    return found


def _batch_channels(
    correlation: NDArray[np.complexfloating[Any, Any]],
    mf: MatchedFilter,
    options: EchoOptions,
    threads: int = 1,
) -> list[ChannelEchoes | None]:
    """:func:`_finish_batch` of :func:`_compiled_batch`, the channels shared out among up to
    ``threads`` threads, in one compiled call (:func:`echoloc.tof._echoes_kernels.batch_channels`):
    the same echoes, without the Python between the two, which a stream's one-frame calls
    would pay every frame; None for the channels left to CLEAN."""
    from echoloc.tof import _echoes_kernels as kernels

    constants, finishing = _kernel_constants(mf, options, _NOISE_STEP, _MAX_SPLITS)
    n_ch = correlation.shape[0]
    out, kept, ok = _batch_outputs(n_ch, options)
    rows = np.ascontiguousarray(correlation, dtype=np.complex64).view(np.float32)
    parts = _kernel_threads(threads, n_ch)
    run_kernel(parts, kernels.batch_channels, parts, rows, mf.n_lags, constants, finishing, out, kept, ok)
    return _channel_echoes(out, kept, ok)


def _batch_outputs(
    n_ch: int, options: EchoOptions
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.bool_]]:
    """What :func:`echoloc.tof._echoes_kernels.batch_channels` writes into for ``n_ch`` channels:
    the delays, amplitudes and SNRs (3, n_ch, slots), their counts, and which channels it kept."""
    out = np.zeros((3, n_ch, 4 * options.max_echoes))
    return out, np.zeros(n_ch, dtype=np.int64), np.zeros(n_ch, dtype=np.bool_)


def _channel_echoes(
    out: NDArray[np.float64], kept: NDArray[np.int64], ok: NDArray[np.bool_]
) -> list[ChannelEchoes | None]:
    """The channels of :func:`echoloc.tof._echoes_kernels.batch_channels`' outputs (None: left to CLEAN)."""
    tof_s, amplitude, snr_db = out[0], out[1], out[2]
    # The counts and flags as Python ints and bools: indexing the arrays element by element
    # made numpy scalars, a large part of what building this list cost.
    return [
        _channel(tof_s[c, :k], amplitude[c, :k], snr_db[c, :k]) if good else None
        for c, (k, good) in enumerate(zip(kept.tolist(), ok.tolist(), strict=True))
    ]


def _channel(
    tof_s: NDArray[np.float64], amplitude: NDArray[np.float64], snr_db: NDArray[np.float64]
) -> ChannelEchoes:
    """``ChannelEchoes(tof_s, amplitude, snr_db)`` as its ``__init__`` builds it, in one dict
    update instead of the frozen class's three ``object.__setattr__`` calls (cheaper, and it
    runs for every channel of every frame)."""
    channel: ChannelEchoes = _new(ChannelEchoes)
    channel.__dict__.update(tof_s=tof_s, amplitude=amplitude, snr_db=snr_db)
    return channel


_new = object.__new__


def _float_rows(frames: NDArray[Any]) -> NDArray[np.float64]:
    """``frames`` (..., samples) as C-contiguous float64 rows (samples): the one type the
    compiled correlation is compiled for (no copy when they already are)."""
    return np.ascontiguousarray(frames, dtype=np.float64).reshape(-1, frames.shape[-1])


def echo_kernel_arguments(
    frames: NDArray[Any], mf: MatchedFilter, options: EchoOptions, threads: int = 1
) -> EchoKernelArguments:
    """The arguments of :func:`echoloc.tof._echoes_kernels.correlate_and_fit` for ``frames`` (...,
    samples), its outputs last: fresh ``out``, ``kept`` and ``ok`` (:func:`_batch_outputs`)."""
    rows = _float_rows(frames)
    n_ch = rows.shape[0]
    out, kept, ok = _batch_outputs(n_ch, options)
    return EchoKernelArguments(rows, *_fixed_kernel_arguments(mf, options, threads, n_ch), out, kept, ok)


def _fixed_kernel_arguments(
    mf: MatchedFilter, options: EchoOptions, threads: int, n_ch: int
) -> tuple[int, int, NDArray[np.complex64], int, int, int, BatchConstants, FinishingConstants]:
    """:func:`echo_kernel_arguments` between the rows and the outputs, made once for each set of
    options, thread count and channel count (a stream's frames repeat them; a memo keyed by the
    options' identity, which it holds, so the key cannot be reused; it spares a frame much of
    the cost of making them). With threads, numba's thread count is still set every call."""
    memo = mf.kernel_arguments_memo
    key = (id(options), threads, n_ch)
    found = memo.get(key)
    if found is None or found[0] is not options:
        if len(memo) >= 64:
            memo.clear()
        constants, finishing = _kernel_constants(mf, options, _NOISE_STEP, _MAX_SPLITS)
        workers = fft_workers(threads, n_ch)
        parts = _kernel_threads(threads, n_ch)
        fixed = (mf.n_fft, mf.n_ifft, mf._spectrum_single, workers, parts, mf.n_lags, constants, finishing)
        found = memo[key] = (options, fixed)
    elif threads > 1:
        _kernel_threads(threads, n_ch)
    return found[1]


def kernel_channels(arguments: EchoKernelArguments) -> list[ChannelEchoes | None]:
    """The channels :func:`echoloc.tof._echoes_kernels.correlate_and_fit` wrote into the outputs of
    its ``arguments`` (:func:`echo_kernel_arguments`); None: left to CLEAN."""
    return _channel_echoes(arguments.out, arguments.kept, arguments.ok)


def _correlated_channels(
    frames: NDArray[Any], mf: MatchedFilter, options: EchoOptions, threads: int = 1
) -> list[ChannelEchoes | None]:
    """:func:`_batch_channels` of the frames' single-precision correlation
    (:meth:`MatchedFilter.correlate_single_rows`), both in one compiled call
    (:func:`echoloc.tof._echoes_kernels.correlate_and_fit`): the same channels, without the
    three calls from Python between them."""
    from echoloc.tof import _echoes_kernels as kernels

    arguments = echo_kernel_arguments(frames, mf, options, threads)
    run_kernel(arguments.parts, kernels.correlate_and_fit, arguments)
    return kernel_channels(arguments)


def _compiled_batch(
    correlation: NDArray[np.complexfloating[Any, Any]],
    mf: MatchedFilter,
    options: EchoOptions,
    noise_step: int = _NOISE_STEP,
    n_samples: int | None = None,
    threads: int = 1,
    max_splits: int | None = None,
) -> _BatchOutput:
    """Run the compiled batch path (:func:`echoloc.tof._echoes_kernels.batch_echoes`) on every channel.

    ``correlation`` is (n_channels, lags); only its first ``n_samples`` lags are read (None:
    all), so the FFT's longer rows (:meth:`MatchedFilter.correlate_single_rows`) go in uncopied.
    With ``threads`` above 1 the channels are shared out among that many threads
    (:func:`echoloc.tof._echoes_kernels.batch_echoes_parallel`).
    """
    from echoloc.tof import _echoes_kernels as kernels  # numba: imported (and compiled) on first use

    n_ch = correlation.shape[0]
    cap = 4 * options.max_echoes
    out_tof = np.zeros((n_ch, cap))
    out_amplitude = np.zeros((n_ch, cap))
    out_count = np.zeros(n_ch, dtype=np.int64)
    out_power = np.zeros(n_ch)
    out_status = np.zeros(n_ch, dtype=np.int64)
    n = correlation.shape[-1] if n_samples is None else n_samples
    if not 0 < n <= correlation.shape[-1]:
        raise ValueError(f"{n} samples asked of correlation rows of {correlation.shape[-1]}")
    parts = _kernel_threads(threads, n_ch)
    run: Callable[..., None] = (
        kernels.batch_echoes if parts == 1 else partial(kernels.batch_echoes_parallel, parts)
    )
    constants, _ = _kernel_constants(
        mf, options, noise_step, _MAX_SPLITS if max_splits is None else max_splits
    )
    run_kernel(
        parts,
        run,
        np.ascontiguousarray(correlation, dtype=np.complex64).view(np.float32),
        n,
        constants,
        out_tof,
        out_amplitude,
        out_count,
        out_power,
        out_status,
    )
    return _BatchOutput(out_tof, out_amplitude, out_count, out_power, out_status == kernels.OK)


def _finish_batch(out: _BatchOutput, mf: MatchedFilter, options: EchoOptions) -> list[ChannelEchoes | None]:
    """:func:`finish_channel` of every channel the batch path fitted, in compiled loops (the same
    formulas; :func:`echoloc.tof._echoes_kernels.finish_channels`); None for the channels it
    hands to CLEAN."""
    from echoloc.tof import _echoes_kernels as kernels

    shape = out.tof.shape
    tof_s, amplitude, snr_db = np.zeros(shape), np.zeros(shape), np.zeros(shape)
    kept = np.zeros(shape[0], dtype=np.int64)
    _, finishing = _kernel_constants(mf, options, _NOISE_STEP, _MAX_SPLITS)
    kernels.finish_channels(
        out.tof,
        out.amplitude,
        out.count,
        out.power,
        out.ok,
        *finishing,
        tof_s,
        amplitude,
        snr_db,
        kept,
    )
    return [
        ChannelEchoes(tof_s[c, :k], amplitude[c, :k], snr_db[c, :k]) if good else None
        for c, (k, good) in enumerate(zip(kept.tolist(), out.ok.tolist(), strict=True))
    ]


def _isolated_echoes(
    correlation: NDArray[np.complexfloating[Any, Any]], mf: MatchedFilter, options: EchoOptions
) -> list[_FastResult | None]:
    """Echoes of every channel (n_channels, n_samples) that stand apart from each other.

    Candidates are the envelope's local maxima above the detection threshold (noise
    power from the median, as CLEAN), less those weaker by more than the dynamic range than
    a certain echo within the template's support of them (:func:`_local_strongest`): a
    strong echo's sidelobes and fine structure, not echoes. Strongest first, a candidate
    is a sidelobe when the echoes already accepted explain it: its magnitude is below 1.5 times the sum
    of their amplitudes times the template's sidelobe envelope at that lag. Each
    accepted echo is fitted as CLEAN fits an isolated echo (envelope parabola, then
    the carrier phase; least-squares amplitude over the main lobe); then echoes within two
    main lobes of each other are fitted jointly and a lone echo by one least-squares step
    (:data:`_LONE_ITERATIONS`). A channel is returned as None, for CLEAN, when two echoes
    lie within a quarter main lobe, when a cluster is too big for one joint fit, when the
    model leaves anything above the threshold around an echo or at a rejected candidate
    or more than CLEAN's split test lets pass over two main lobes, or when it has more
    candidates than ``4 max_echoes``.
    """
    n_ch, n = correlation.shape
    power_map = correlation.real**2 + correlation.imag**2
    power = np.maximum(np.median(power_map, axis=1) / _LN2, np.finfo(float).tiny)
    threshold = 10 ** (options.threshold_db / 10) * power
    first = max(mf.first_lag(options.blanking_s), 1)
    ch, k = np.nonzero(power_map[:, first : n - 1] > threshold[:, None])
    k = k + first
    peak = (power_map[ch, k] > power_map[ch, k - 1]) & (power_map[ch, k] >= power_map[ch, k + 1])
    ch, k = ch[peak], k[peak]
    # Candidates weaker by more than the dynamic range than a certain echo within the template's
    # support of them are dropped (its residue and sidelobes), as CLEAN does not look there.
    local = _local_strongest(ch, k, power_map[ch, k], mf.residue_lags)
    strongest = np.zeros(n_ch)
    np.maximum.at(strongest, ch, power_map[ch, k])
    loud = (power_map[ch, k] >= local * 10 ** (-options.dynamic_range_db / 10)) & (
        power_map[ch, k] >= strongest[ch] * _PRECISION_POWER
    )
    ch, k = ch[loud], k[loud]
    results: list[_FastResult | None] = [(np.zeros(0), np.zeros(0), float(p)) for p in power]
    if len(ch) == 0:
        return results
    # Candidates per channel, strongest first, padded to K columns.
    strength = np.sqrt(power_map[ch, k])
    order = np.lexsort((-strength, ch))
    ch, k, strength = ch[order], k[order], strength[order]
    counts = np.bincount(ch, minlength=n_ch)
    rank = np.arange(len(ch)) - np.repeat(np.cumsum(counts) - counts, counts)
    # A channel with more candidates than 4 x max_echoes goes to CLEAN; the rest fit in
    # a table of that many columns.
    too_many = counts > 4 * options.max_echoes
    width = int(min(counts.max(), 4 * options.max_echoes))
    kept = rank < width
    cand_k = np.zeros((n_ch, width), dtype=np.int64)
    cand_a = np.zeros((n_ch, width))
    cand_k[ch[kept], rank[kept]] = k[kept]
    cand_a[ch[kept], rank[kept]] = strength[kept]
    dilated = _sidelobe_envelope(mf)
    mainlobe = mf.mainlobe_lags
    # Strongest first, a candidate is an echo unless the echoes already accepted explain it.
    accepted = np.zeros((n_ch, width), dtype=bool)
    for j in range(width):
        gap = np.abs(cand_k[:, :j] - cand_k[:, j : j + 1]) + mf.half_width
        inside = gap <= 2 * mf.half_width
        side = np.where(inside & accepted[:, :j], dilated[np.clip(gap, 0, 2 * mf.half_width)], 0.0)
        bound = np.sum(side * cand_a[:, :j], axis=1)
        accepted[:, j] = (cand_a[:, j] > 1.5 * bound) & (cand_a[:, j] > 0)
    # Fit every accepted echo alone, then again with the others' sidelobes taken out
    # (two passes: the sidelobes are below 1/PSLR, so the fits settle at once).
    ach, aj = np.nonzero(accepted)
    peak_k = cand_k[ach, aj]
    fit_half = max(1, round(mainlobe / 2))
    neighbours = np.clip(peak_k[:, None] + np.arange(-1, 2), 0, n - 1)
    window = peak_k[:, None] + np.arange(-fit_half, fit_half + 1)
    in_frame = (window >= 0) & (window < n)
    window = np.clip(window, 0, n - 1)
    values = correlation[ach[:, None], neighbours].astype(complex)
    window_values = np.where(in_frame, correlation[ach[:, None], window].astype(complex), 0)
    tof, amplitude = _fit_peaks(mf, values, neighbours, window_values, window)
    own = np.arange(len(ach))
    for _ in range(2):
        others_near = _model_at(mf, ach, tof, amplitude, ach, neighbours, exclude=own)
        others_window = _model_at(mf, ach, tof, amplitude, ach, window, exclude=own)
        tof, amplitude = _fit_peaks(
            mf, values - others_near, neighbours, np.where(in_frame, window_values - others_window, 0), window
        )
    # Echoes within two main lobes of each other (CLEAN's clusters) are fitted jointly, and a
    # lone echo is refined by real-amplitude steps (:data:`_LONE_ITERATIONS`).
    order = np.lexsort((tof, ach))
    ach, tof, amplitude, peak_k = ach[order], tof[order], amplitude[order], peak_k[order]
    window, in_frame = window[order], in_frame[order]
    new_group = np.ones(len(ach), dtype=bool)
    new_group[1:] = (np.diff(ach) != 0) | (np.diff(tof) >= 2 * mainlobe)
    group = np.cumsum(new_group) - 1
    bad = too_many.copy()
    sizes = np.bincount(group)
    # Echoes that CLEAN would merge, and clusters too big for one joint fit, go to CLEAN.
    close = (np.diff(ach) == 0) & (np.diff(tof) < mainlobe / 4)
    bad[ach[1:][close]] = True
    bad[ach[sizes[group] > _MAX_JOINT]] = True
    # Every fit takes the other echoes' sidelobes from the single fits, not from each other.
    single_tof, single_amplitude = tof.copy(), amplitude.copy()
    joint = (sizes[group] > 1) & ~bad[ach]
    if np.any(joint):
        tof[joint], amplitude[joint] = _fit_clusters(
            mf,
            correlation,
            ach,
            single_tof,
            single_amplitude,
            group,
            joint,
            fit_half,
            _COMPLEX_ITERATIONS,
            _REAL_ITERATIONS,
        )
    lone = (sizes[group] == 1) & ~bad[ach]
    if np.any(lone) and _LONE_ITERATIONS > 0:
        tof[lone], amplitude[lone] = _fit_clusters(
            mf, correlation, ach, single_tof, single_amplitude, group, lone, fit_half, 0, _LONE_ITERATIONS
        )
    # Checks: the model explains the data around each echo (its main lobe) and at every
    # rejected candidate (one sample), sidelobes included; and over two main lobes around
    # each echo it leaves no more than CLEAN's split test lets pass (:meth:`_Clean._choose_order`).
    rejected_ch, rejected_j = np.nonzero(~accepted & (cand_a > 0))
    for probe_ch, probe in (
        (ach, window),
        (rejected_ch, cand_k[rejected_ch, rejected_j][:, None]),
    ):
        left = np.abs(
            correlation[probe_ch[:, None], probe].astype(complex)
            - _model_at(mf, ach, tof, amplitude, probe_ch, probe)
        )
        bad[probe_ch[np.any(left**2 > threshold[probe_ch, None], axis=1)]] = True
    span = math.ceil(mainlobe)
    around = np.round(tof).astype(np.int64)[:, None] + np.arange(-span, span + 1)
    inside = (around >= 0) & (around < n)
    around = np.clip(around, 0, n - 1)
    model = _model_at(mf, ach, tof, amplitude, ach, around)
    left = np.where(inside, correlation[ach[:, None], around].astype(complex) - model, 0)
    cost = np.sum(left.real**2 + left.imag**2, axis=1)
    acf_energy = mf.acf_energy
    unexplained = (cost >= 3.0 * power[ach] * np.sum(inside, axis=1)) & (
        cost >= 0.003 * np.abs(amplitude) ** 2 * acf_energy
    )
    bad[ach[unexplained]] = True
    for channel in range(n_ch):
        if bad[channel]:
            results[channel] = None
    mine = ~bad[ach]
    for channel in np.unique(ach[mine]):
        rows = mine & (ach == channel)
        results[channel] = (tof[rows], np.abs(amplitude[rows]), float(power[channel]))
    return results


def _window_max(
    ch: NDArray[np.int64], k: NDArray[np.int64], values: NDArray[Any], reach: int
) -> NDArray[Any]:
    """For each candidate (sorted by channel, then lag ``k``), the largest of ``values`` over
    the candidates of its channel within ``reach`` lags of it, itself included."""
    out = values.copy()
    for step in range(1, len(values)):
        near = (ch[step:] == ch[:-step]) & (k[step:] - k[:-step] <= reach)
        if not np.any(near):
            break  # lags ascend within a channel: candidates farther apart in the order are too
        out[step:] = np.where(near, np.maximum(out[step:], values[:-step]), out[step:])
        out[:-step] = np.where(near, np.maximum(out[:-step], values[step:]), out[:-step])
    return out


def _local_strongest(
    ch: NDArray[np.int64], k: NDArray[np.int64], power: NDArray[Any], reach: int
) -> NDArray[Any]:
    """The dynamic range's reference for each candidate (sorted by channel, then lag): the
    largest ``power`` among the candidates within ``reach`` lags of it that are the largest
    within ``reach`` lags of themselves, 0 if none.

    Such a candidate is an echo for certain (no stronger echo's sidelobes reach it, so the
    sidelobe test accepts it), while any other may be a sidelobe: taking every candidate as a
    reference would carry a strong echo's reach on through its own sidelobes, twice the
    template's support. (:func:`echoloc.tof._echoes_kernels._local_floor` in compiled loops.)
    """
    peaks = _window_max(ch, k, power, reach)
    return _window_max(ch, k, np.where(power >= peaks, power, 0.0), reach)


_MAX_JOINT = 4
"""The largest cluster the batched joint fit takes (larger ones go to CLEAN)."""
_CLEAN_COMPLEX_ITERATIONS = 200
_CLEAN_REAL_ITERATIONS = 200
"""Most Levenberg-Marquardt steps of CLEAN's joint fits and model choice (complex, then
real amplitudes); each stops once converged. They start from successive refinement or
from guesses a quarter to half a main lobe off: with 8 + 6 fixed steps 88 % of the 7 mm
pairs were found, with 25 + 15 all of them but the random 1 m^3 recording lost 8 of
1172 reflectors to splits that had not settled back together."""
_CLEAN_COMPLEX_TOLERANCE = 1e-3
"""CLEAN's complex-amplitude fits stop once a step moves no delay by more than this, samples
(the real-amplitude fits: 1e-6). They only choose the basin the real-amplitude fit settles
in, half a carrier cycle (2 samples) wide: on the five-reflector bench scene's fits, 1e-3
instead of 1e-6 halves their steps and changes 1 final fit of 430."""
_CLEAN_COMPLEX_GAIN = 1e-2
"""CLEAN's complex-amplitude fits also stop once an accepted step lowers the cost by less than
this fraction of it (the real-amplitude fits: never): there they crawl along the valley floor
of their basin (Gauss-Newton steps on the table's piecewise-linear slopes zig-zag by a hundredth
of a sample) or drift a faint echo outward. On the bench scenes' CLEAN channels this shortens
the candidate fits and moves no answer by more than 1e-9 samples."""
_LONE_ITERATIONS = 1
"""Levenberg-Marquardt steps (real amplitude) of the batch path's fit of an echo with no
neighbour within two main lobes, from its phase-refined estimate. The carrier phase at
three lags fits an echo of exactly the template's shape; an echo that differs from it (the
transducers' response off their axis) is fitted better by least squares over its main lobe.
At decimation 2, where the three lags span 4 samples, the difference reached the residual
checks: without this step 33 of the report scene's 160 channels (all on the receiver whose
third-ball echo fits the template worst) went to CLEAN, with it 1. One step settles it: more
moved no delay of the calibration test's by 0.01 ns."""
_MAX_SPLITS = 2
"""Echoes a channel's batch path may split in two (:func:`echoloc.tof._echoes_kernels._split_echo`)
when its model leaves one unexplained, before the channel goes to CLEAN."""
_COMPLEX_ITERATIONS = 2
_REAL_ITERATIONS = 3
"""Levenberg-Marquardt steps of the batched cluster fits: they start from the
phase-refined single fits and settle in two (a fit that does not is caught by the
residual checks and handed to CLEAN)."""


def _fit_clusters(
    mf: MatchedFilter,
    correlation: NDArray[np.complexfloating[Any, Any]],
    ach: NDArray[np.int64],
    tof: NDArray[np.float64],
    amplitude: NDArray[np.complex128],
    group: NDArray[np.int64],
    joint: NDArray[np.bool_],
    fit_half: int,
    complex_iterations: int,
    real_iterations: int,
) -> tuple[NDArray[np.float64], NDArray[np.complex128]]:
    """Joint fits of every cluster of echoes (``joint`` rows, sorted by channel and delay).

    As :meth:`_Clean._joint_fit`: the data are the correlation over the cluster's span
    (a half main lobe beyond its first and last echo) less the other echoes' sidelobes;
    ``complex_iterations`` steps with complex amplitudes (none: skipped), then
    ``real_iterations`` with real ones from there. Returns the fitted delays and
    amplitudes of the ``joint`` rows.
    """
    n = correlation.shape[1]
    rows = np.flatnonzero(joint)
    ids, first, counts = np.unique(group[rows], return_index=True, return_counts=True)
    k = int(counts.max())
    slot = np.arange(len(rows)) - np.repeat(first, counts)
    cluster = np.repeat(np.arange(len(ids)), counts)
    tofs = np.zeros((len(ids), k))
    amps = np.zeros((len(ids), k), dtype=complex)
    active = np.zeros((len(ids), k), dtype=bool)
    tofs[cluster, slot] = tof[rows]
    amps[cluster, slot] = amplitude[rows]
    active[cluster, slot] = True
    channel = ach[rows[first]]
    lo = np.floor(tof[rows[first]]).astype(np.int64) - fit_half
    hi = np.ceil(tof[rows[first + counts - 1]]).astype(np.int64) + fit_half + 1
    width = int(np.max(hi - lo))
    samples = lo[:, None] + np.arange(width)
    valid = (samples < hi[:, None]) & (samples >= 0) & (samples < n)
    samples = np.clip(samples, 0, n - 1)
    # Inactive slots sit on the first echo (zero weight) so the table lookup stays in range.
    tofs = np.where(active, tofs, tofs[:, :1])
    others = _model_at(mf, ach, tof, amplitude, channel, samples, exclude=ids, echo_group=group)
    data = np.where(valid, correlation[channel[:, None], samples].astype(complex) - others, 0)
    if complex_iterations:
        tofs, amps, _ = _joint_fit_batch(
            mf, data, samples, valid, tofs, amps, active, real=False, iterations=complex_iterations
        )
    amps = np.where(amps.real >= 0, np.abs(amps), -np.abs(amps)).astype(complex)
    tofs, amps, _ = _joint_fit_batch(
        mf, data, samples, valid, tofs, amps, active, real=True, iterations=real_iterations
    )
    return tofs[cluster, slot], amps[cluster, slot]


def finish_channel(
    tof_s: NDArray[np.float64],
    amplitude: NDArray[np.float64],
    snr_db: NDArray[np.float64],
    options: EchoOptions,
    support_s: float = math.inf,
) -> ChannelEchoes:
    """Drop blanked and sub-threshold echoes, and echoes weaker by more than the dynamic range
    than an echo within ``support_s`` of them; sort by arrival.

    ``support_s`` is how far an echo's residue reaches (the matched filter's:
    :attr:`MatchedFilter.support_s`); infinite (the default, the envelope estimators'), every
    echo of the channel: the floor is then the strongest echo's.
    """
    floor = amplitude * 10 ** (-options.dynamic_range_db / 20)
    # (not >: a delay that is not a number is near every echo, and dropped below anyway)
    near = ~(np.abs(tof_s[:, None] - tof_s[None, :]) > support_s)
    faint = np.any(near & (amplitude[:, None] < floor[None, :]), axis=1)
    faint |= amplitude < (float(amplitude.max()) if len(amplitude) else 0.0) * _PRECISION_AMPLITUDE
    keep = (tof_s >= options.blanking_s) & (snr_db >= options.threshold_db) & ~faint & np.isfinite(tof_s)
    order = np.argsort(tof_s[keep], kind="stable")
    return ChannelEchoes(tof_s[keep][order], amplitude[keep][order], snr_db[keep][order])


def frame_time_s(recording: Recording, index: int) -> float:
    """Start time of frame ``index``: ``frame_times`` if recorded, else back-to-back frames."""
    if recording.frame_times_s is not None:
        return float(recording.frame_times_s[index])
    return index * recording.n_samples / recording.sample_rate_hz
