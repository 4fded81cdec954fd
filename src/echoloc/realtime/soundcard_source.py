"""Capture from a sound card: the head's pulse out of one output, its microphones in (docs/SOUNDCARD.md).

The bench set-up: ultrasonic MEMS microphones and a tweeter or piezo on a USB audio interface at
192 kHz or more. :class:`SoundCardSource` opens one full-duplex PortAudio stream (through
sounddevice) at the head's sample rate. Its callback writes the head's pulse on
``channels.output`` once every frame period (``1 / frame_rate_hz`` rounded to whole samples, so
emissions never drift against the card's clock) and copies every input block into a
preallocated ring; a worker thread cuts frames out of the ring and hands them on.

Frame ``k`` spans input samples ``[e_k, e_k + n_samples)``, where ``e_k`` is the input-sample
index of emission ``k``: the instant the pulse leaves the card, as the input sees it. Two ways to
know it:

- **loopback** (``channels.loopback`` in the head: the drive, through a divider, on a spare
  input): the pulse is found in that input by matched filter (cross-correlation with the emitted
  pulse, a parabolic peak refined on the band-limited correlation) each frame. The first pulse is
  searched for up to ``max_latency_s`` after it is written, later ones within ``track_samples``
  of where the last was. It is exact to a small fraction of a sample (noise and the loopback's
  level set how small: the jitter is reported by :meth:`SoundCardSource.emission`), and it
  includes everything the driver does not report: the converters' digital filters, USB
  buffering, a host API that misstates its latency;
- **latency** (no loopback): ``e_k`` is the output index of the pulse plus the latency the
  driver reports, ``outputBufferDacTime - inputBufferAdcTime`` of each callback (the median of
  the recent ones; ``stream.latency`` input + output when the callback times are 0). Exact only
  to what the driver reports: often a few samples to a few milliseconds off. A fixed error of
  ``k`` samples puts every path ``c k / fs`` short (too long, if the driver says too little),
  every range about half that: a receiver delay that ``echoloc calibrate`` measures and takes off.

``e_k`` is fractional: the frame is cut at the nearest sample and moved by the remaining fraction
with a band-limited (Kaiser-windowed sinc) fractional delay, unless that fraction is below
:data:`EXACT_FRACTION` (then the samples are the card's, untouched).

A frame is stamped with PortAudio's stream time of its emission (the input clock's time of
``e_k``) and numbered ``k``. PortAudio's status flags (input overflow and underflow, output
underflow) are counted in :attr:`SoundCardSource.xruns` and warned about: samples are missing
or made up there, so the frames in flight across one (emitted before it, not yet complete) are
dropped, and counted lost by the gap they leave in the numbering; the frames emitted after it
go on (with a loopback the pulse is searched for afresh around where the driver's latency puts
it). A worker that falls so far behind that the ring overwrote a frame drops it likewise.
"""

from __future__ import annotations

import contextlib
import math
import statistics
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.fft
import scipy.signal
from numpy.typing import NDArray

from echoloc.errors import EchoLocError
from echoloc.extras import missing_extra
from echoloc.io.head import SensorHead
from echoloc.io.recording import Recording
from echoloc.realtime.capture import CaptureSource
from echoloc.realtime.stream import FrameQueue
from echoloc.realtime.transport import WARN_INTERVAL_S

DEFAULT_AMPLITUDE = 0.7
"""The pulse's peak on the output, of full scale: 3 dB below it, so that the DAC's
reconstruction (whose peaks between samples exceed the samples') does not clip."""

MAX_LATENCY_S = 0.25
"""How long after it is written the first pulse is searched for on the loopback input, s."""

TRACK_SAMPLES = 16
"""Once found, each pulse is looked for within this many samples of where the last one was."""

LOOPBACK_MIN_CORRELATION = 0.5
"""The normalised correlation (1: the loopback is the pulse exactly, scaled) a pulse on the
loopback input needs to be taken for one."""

EXACT_FRACTION = 1e-3
"""A fractional part of the emission index below this, samples (1.8 µm of path at 192 kHz), is
left alone: the frame is the card's samples, not interpolated."""

FRACTION_TAPS = 32
"""The fractional delay's half-length, samples: a Kaiser-windowed sinc of 2 * 32 + 1 taps."""
_KAISER_BETA = 8.0

START_DELAY_S = 0.05
"""The first pulse is written this long after the stream starts (its first buffers can be
priming or silence)."""

RING_S = 2.0
"""The input ring's length, s: how far the worker may fall behind before samples are lost."""

CLIP_LEVEL = 0.999
"""An input sample at or above this, of full scale, is taken as clipped (warned about)."""

_LATENCY_HISTORY = 32
"""Callbacks whose reported latency the median is taken over."""
_BLOCK_RING = 1 << 13
"""Callbacks the ring's bookkeeping holds (each: start, length, times, status)."""
_POLL_S = 0.002
"""How long the worker waits for more input when it needs it, s."""

_INPUT_OVERFLOW, _INPUT_UNDERFLOW, _OUTPUT_UNDERFLOW, _OUTPUT_OVERFLOW = 1, 2, 4, 8
_FLAG_NAMES = {
    _INPUT_OVERFLOW: "input_overflow",
    _INPUT_UNDERFLOW: "input_underflow",
    _OUTPUT_UNDERFLOW: "output_underflow",
    _OUTPUT_OVERFLOW: "output_overflow",
}
_BREAKS = _INPUT_OVERFLOW | _INPUT_UNDERFLOW | _OUTPUT_UNDERFLOW
"""The flags after which input and output no longer keep the same distance in samples."""
_WHAT = {
    "input_overflow": "input overflow (input samples were lost)",
    "input_underflow": "input underflow (silence was put in the input)",
    "output_underflow": "output underflow (a gap was put in the output)",
    "output_overflow": "output overflow",
}


def sounddevice_backend() -> Any:
    """The sounddevice module, or the error that says what to install."""
    try:
        import sounddevice
    except ImportError:
        error = missing_extra("soundcard", "capture from a sound card")
        raise EchoLocError(
            f"{error} (it also needs the PortAudio library: on Linux the package libportaudio2)"
        ) from None
    except OSError as error:  # sounddevice is there, PortAudio is not
        raise EchoLocError(
            f"capture from a sound card needs the PortAudio library, which sounddevice cannot load "
            f"({error}): install it (Debian, Ubuntu: sudo apt install libportaudio2; Fedora: "
            f"portaudio; macOS and Windows: pip install --force-reinstall sounddevice, whose wheels "
            f"carry it)"
        ) from None
    return sounddevice


@dataclass(frozen=True)
class Emission:
    """Where emission ``frame`` was found: written at output sample ``output_index``, seen at
    input sample ``input_index`` (fractional), ``time_s`` on the stream clock; ``correlation``:
    the loopback's normalised correlation with the pulse (NaN without a loopback)."""

    frame: int
    output_index: int
    input_index: float
    time_s: float
    correlation: float = math.nan

    @property
    def latency_samples(self) -> float:
        return self.input_index - self.output_index


@dataclass(frozen=True)
class EmissionReport:
    """How the emission instant is known, as measured so far (:meth:`SoundCardSource.emission`).

    ``method``: ``"loopback"`` or ``"latency"``; ``frames``: emissions measured since the last
    break (start, overflow); ``latency_samples``: their mean input-minus-output distance;
    ``jitter_samples``: its standard deviation (0 for one frame); ``reported_latency_samples``:
    what the driver reports (the median of recent callbacks); ``reported_error_samples``: that
    minus what the loopback measured (NaN without one): the error the latency method would make;
    ``loopback_gain``: the loopback's level against the pulse written; ``correlation``: the
    lowest normalised correlation of the pulses found (NaN without a loopback).
    """

    method: str
    frames: int
    latency_samples: float
    jitter_samples: float
    reported_latency_samples: float
    reported_error_samples: float
    loopback_gain: float
    correlation: float
    sample_rate_hz: float

    def range_error_m(self, speed_of_sound_m_s: float) -> float:
        """The range error the driver's latency would leave without the loopback, m:
        ``c * reported_error_samples / fs / 2`` (positive: ranges too short)."""
        return speed_of_sound_m_s * self.reported_error_samples / self.sample_rate_hz / 2


class _Welford:
    def __init__(self) -> None:
        self.n = 0
        self.mean = 0.0
        self._m2 = 0.0

    def add(self, value: float) -> None:
        self.n += 1
        delta = value - self.mean
        self.mean += delta / self.n
        self._m2 += delta * (value - self.mean)

    @property
    def std(self) -> float:
        return math.sqrt(self._m2 / (self.n - 1)) if self.n > 1 else 0.0 if self.n else math.nan


class _Pulse:
    """The emitted pulse as a matched filter: find it in a stretch of the loopback input.

    The pulse is found on the correlation's envelope (the analytic correlation's magnitude: its
    height does not depend on where between two samples the pulse lies), its polarity read from
    the analytic correlation's phase there (an amplifier may invert the drive), and its lag on
    the carrier's lobe of that polarity nearest the envelope's peak. Taking the largest |c| instead
    can pick the lobe half a carrier period off, when the pulse lies halfway between two samples.
    """

    def __init__(self, samples: NDArray[np.float64], samples_per_cycle: float | None) -> None:
        self.samples = samples
        self.length = len(samples)
        self.norm = float(np.linalg.norm(samples))
        # Integer lags either side of the envelope's peak where the carrier's lobe may lie.
        self.reach = max(1, int(samples_per_cycle // 2)) if samples_per_cycle else 1
        self._spectra: dict[int, NDArray[np.complex128]] = {}

    def _spectrum(self, n_fft: int) -> NDArray[np.complex128]:
        spectrum = self._spectra.get(n_fft)
        if spectrum is None:
            if len(self._spectra) > 8:
                self._spectra.clear()
            spectrum = np.conj(scipy.fft.rfft(self.samples, n_fft))
            self._spectra[n_fft] = spectrum
        return spectrum

    def find(
        self, x: NDArray[np.float64], *, first: bool, min_correlation: float
    ) -> tuple[float, float, float] | None:
        """The pulse in ``x``: ``(lag, gain, correlation)`` with ``x[lag + t] ~ gain * pulse[t]``
        (``lag`` fractional; ``correlation`` the envelope's, normalised: 1 for the pulse exactly,
        scaled), or None if no lag correlates ``min_correlation`` or better. ``first``: the
        earliest pulse, else the strongest. A pulse within a lobe of either end of the lags searched
        is not taken (it may lie beyond)."""
        n_lags = len(x) - self.length + 1
        if n_lags < 2 * self.reach + 3:
            return None
        n_fft = scipy.fft.next_fast_len(len(x) + self.length)
        spectrum = scipy.fft.rfft(x, n_fft) * self._spectrum(n_fft)
        real = scipy.fft.irfft(spectrum, n_fft)[:n_lags]
        one_sided = np.zeros(n_fft, dtype=np.complex128)
        one_sided[: len(spectrum)] = spectrum
        one_sided[1 : (n_fft + 1) // 2] *= 2.0
        analytic = scipy.fft.ifft(one_sided)[:n_lags]
        envelope = np.abs(analytic)
        energy = np.cumsum(np.concatenate(([0.0], x * x)))
        window = (energy[self.length :] - energy[: -self.length])[:n_lags]
        ncc = envelope / (self.norm * np.sqrt(np.maximum(window, 1e-30)))
        # Only lags whose window holds a good part of the loudest one's energy: before a pulse the
        # envelope's Hilbert part decays slowly (as 1 / lag), and over near silence its ratio to
        # next to no energy would pass for a match.
        loud = window >= 0.25 * float(np.max(window))
        strong = np.flatnonzero(loud & (ncc >= min_correlation))
        if len(strong) == 0:
            return None
        if first:
            start = int(strong[0])
            peak = start + int(np.argmax(envelope[start : start + self.length]))
        else:
            peak = int(np.argmax(np.where(loud & (ncc >= min_correlation), envelope, 0.0)))
        sign = 1.0 if analytic[peak].real >= 0 else -1.0
        lo, hi = peak - self.reach, peak + self.reach + 1
        if lo < 1 or hi > n_lags - 1:
            return None
        lobe = lo + int(np.argmax(sign * real[lo:hi]))
        lag, value = _refine_peak(spectrum, n_fft, lobe, sign, real[lobe - 1 : lobe + 2])
        return lag, value / self.norm**2, float(ncc[peak])


def _refine_peak(
    spectrum: NDArray[np.complex128], n_fft: int, peak: int, sign: float, around: Any
) -> tuple[float, float]:
    """The correlation's extremum near integer ``peak`` (a maximum of ``sign * c``) and its value
    there: a parabola through the three samples ``around`` it (``c[peak - 1 : peak + 2]``), then
    Newton's steps on the band-limited (trigonometric) interpolation of the correlation, from its
    ``spectrum``. The parabola alone is off by up to a few hundredths of a sample on a carrier's
    lobe; the steps take it to where the interpolated correlation's slope is 0."""
    left, mid, right = (sign * float(v) for v in around)
    curvature = left - 2 * mid + right
    offset = 0.5 * (left - right) / curvature if curvature < 0 else 0.0
    parabola = (peak + offset, sign * (mid - 0.25 * (left - right) * offset))
    weights = np.full(len(spectrum), 2.0)
    weights[0] = 1.0
    if n_fft % 2 == 0:
        weights[-1] = 1.0
    omega = 2 * np.pi * np.arange(len(spectrum)) / n_fft
    # c(peak + d) = Re sum_k b_k exp(i omega_k d): the origin at the peak keeps the phases small.
    b = sign * weights * spectrum * np.exp(1j * omega * peak) / n_fft
    b1, b2 = b * (1j * omega), b * -(omega**2)
    d = offset
    for _ in range(8):
        phase = np.exp(1j * omega * d)
        slope = float(np.real(np.dot(b1, phase)))
        bend = float(np.real(np.dot(b2, phase)))
        if bend >= 0:
            return parabola
        step = min(max(-slope / bend, -0.5), 0.5)
        d += step
        if abs(step) < 1e-9:
            break
    if abs(d) > 1.0:
        return parabola
    return peak + d, sign * float(np.real(np.dot(b, np.exp(1j * omega * d))))


def _fraction_taps(fraction: float, half: int = FRACTION_TAPS) -> NDArray[np.float64]:
    """Taps ``g[j]``, j = -half..half, with ``sum_j x[n + j] g[j] ~ x(n + fraction)`` for a
    band-limited x: a sinc under a Kaiser window (beta 8), at unit gain at 0 Hz."""
    u = np.arange(-half, half + 1) - fraction
    window = np.i0(_KAISER_BETA * np.sqrt(np.clip(1.0 - (u / (half + 1)) ** 2, 0.0, 1.0))) / np.i0(
        _KAISER_BETA
    )
    taps = np.sinc(u) * window
    return np.asarray(taps / taps.sum(), dtype=np.float64)


def _status_bits(status: Any) -> int:
    if not status:
        return 0
    bits = 0
    for bit, name in _FLAG_NAMES.items():
        if getattr(status, name, False):
            bits |= bit
    return bits


def _describe(device: Any) -> str:
    return "the default device" if device is None else repr(device)


class SoundCardSource(CaptureSource):
    """Frames of a sound card, the head's pulse emitted every frame period, into ``frames``.

    Parameters
    ----------
    head
        The head on the card: ``acquisition.sample_rate_hz`` is the stream's rate, ``channels``
        the inputs (``order``, ``loopback``, ``count``: the inputs opened) and ``output`` the
        output driving the transmitter; ``[adc]`` how a float sample becomes the counts a frame
        carries (``float32`` with ``full_scale = 1.0`` keeps a 24-bit card's resolution).
    frames
        Where the session, the frames and the end go.
    device
        The PortAudio device: its index, part of its name, or an (input, output) pair; None:
        the default. ``python -m sounddevice`` lists them.
    amplitude
        The pulse's peak on the output, of full scale (0 < amplitude <= 1).
    backend
        The sounddevice module or a stand-in with its ``Stream``, ``query_devices``,
        ``check_input_settings``, ``check_output_settings``, ``PortAudioError`` and
        ``CallbackAbort``; None imports sounddevice.
    blocksize
        Frames a callback handles (0: what the host finds best).
    latency
        PortAudio's suggested latency: ``"low"``, ``"high"`` or seconds.
    max_latency_s, track_samples
        How far the first pulse is searched for on the loopback input, and how far from
        where the last was each next one (:data:`MAX_LATENCY_S`, :data:`TRACK_SAMPLES`).
    accept_session
        As :class:`~echoloc.realtime.capture.CaptureSource`.
    """

    kind = "soundcard"

    def __init__(
        self,
        head: SensorHead,
        frames: FrameQueue,
        *,
        device: int | str | tuple[int | str | None, int | str | None] | None = None,
        amplitude: float = DEFAULT_AMPLITUDE,
        backend: Any = None,
        blocksize: int = 0,
        latency: str | float = "low",
        max_latency_s: float = MAX_LATENCY_S,
        track_samples: int = TRACK_SAMPLES,
        ring_s: float = RING_S,
        accept_session: Callable[[Recording], object] | None = None,
        warn_interval_s: float = WARN_INTERVAL_S,
    ) -> None:
        super().__init__(head, frames, accept_session=accept_session, warn_interval_s=warn_interval_s)
        self.device = device
        self._check_head(head)
        if not (isinstance(amplitude, int | float) and 0 < amplitude <= 1):
            raise EchoLocError(f"the pulse's amplitude must be in (0, 1] (of full scale), got {amplitude!r}")
        if not (max_latency_s > 0 and track_samples >= 2 and ring_s > 0):
            raise EchoLocError("max_latency_s and ring_s must be > 0 s and track_samples >= 2")
        self.amplitude = float(amplitude)
        self.sample_rate_hz = float(head.header.sample_rate_hz)
        fs = self.sample_rate_hz
        self.period = round(fs / head.frame_rate_hz)
        """Samples between emissions: the frame rate's period, rounded (the frame rate is fs / period)."""
        drive = self._emitted_pulse(head)
        if len(drive) >= self.period:
            raise EchoLocError(
                f"{head.source}: the pulse ({len(drive)} samples) is longer than the frame period "
                f"({self.period} samples at {head.frame_rate_hz:g} Hz)"
            )
        carrier = head.header.carrier_hz
        self._pulse = _Pulse(drive, fs / carrier if carrier else None)
        self._drive = (self.amplitude * drive).astype(np.float32)
        self.n_inputs = head.n_channels
        assert head.output_channel is not None
        self.output_channel = head.output_channel
        self.n_outputs = head.output_channel + 1
        self.first_emission = round(START_DELAY_S * fs)
        """The output-sample index of emission 0; emission k is at ``first_emission + k * period``."""
        self.blocksize = blocksize
        self.suggested_latency = latency
        self.max_latency = round(max_latency_s * fs)
        self.track = int(track_samples)
        self.loopback = head.loopback_channel
        needed = self.max_latency + self.period + head.n_samples + 2 * len(drive) + 4 * FRACTION_TAPS
        self._ring_size = max(round(ring_s * fs), 2 * needed)
        self._ring = np.zeros((self._ring_size, self.n_inputs), dtype=np.float32)
        self._block_start = np.zeros(_BLOCK_RING, dtype=np.int64)
        self._block_frames = np.zeros(_BLOCK_RING, dtype=np.int64)
        self._block_adc = np.zeros(_BLOCK_RING)
        self._block_dac = np.zeros(_BLOCK_RING)
        self._block_now = np.zeros(_BLOCK_RING)
        self._block_flags = np.zeros(_BLOCK_RING, dtype=np.int64)
        self._written = 0  # input samples in the ring so far (the output's index too): the callback's
        self._n_blocks = 0  # callbacks so far: the callback's
        self._callback_error: BaseException | None = None
        self.xruns: dict[str, int] = dict.fromkeys(_FLAG_NAMES.values(), 0)
        """PortAudio's status flags seen, by name (each callback that had it counts one)."""
        self.emissions: deque[Emission] = deque(maxlen=256)
        """The latest emissions found (for a bench's checks)."""
        self._peaks = np.zeros(self.n_inputs)
        self._stats = _Welford()
        self._reported_median = math.nan
        self._report_lock = threading.Lock()
        self._gain = math.nan
        self._min_correlation = math.nan
        self._stream: Any = None
        self._sd = sounddevice_backend() if backend is None else backend
        self._check_device()
        if self.loopback is None:
            self._warnings.add(
                "loopback",
                f"{self.address}: the head has no channels.loopback: the emission instant is the "
                "latency the driver reports, often a few samples to milliseconds off (a range bias "
                "`echoloc calibrate` can take off); a loopback makes it exact (docs/SOUNDCARD.md)",
            )

    # -- checks

    @staticmethod
    def _check_head(head: SensorHead) -> None:
        where = head.source
        if head.output_channel is None:
            raise EchoLocError(
                f"{where}: a sound card's head needs channels.output, the output to the transmitter"
            )
        if len(head.header.transmitters_m) != 1:
            n_tx = len(head.header.transmitters_m)
            raise EchoLocError(f"{where}: a sound card drives one transmitter; the head has {n_tx}")
        if head.header.signal_kind != "rf":
            raise EchoLocError(f"{where}: a sound card records rf, the head says {head.header.signal_kind!r}")
        rate = head.sensor_tables.get("acquisition", {}).get("sample_rate_hz")
        if rate is not None and float(rate) != float(head.header.sample_rate_hz):
            raise EchoLocError(
                f"{where}: a sound card records at acquisition.sample_rate_hz ({rate:g} Hz); "
                f"the head's receiver has output_rate_hz {head.header.sample_rate_hz:g}"
            )

    @staticmethod
    def _emitted_pulse(head: SensorHead) -> NDArray[np.float64]:
        """The pulse the transmitter is driven with (peak 1): the scene's emitted waveform (the
        header's is what comes back, through the transducers' responses when the head models
        them)."""
        scene = head.scene({"reflectors": [{"position_m": [0.0, 0.0, 1.0]}]})
        return np.asarray(scene.waveform(0).samples, dtype=np.float64)

    def _device_error(self, why: object) -> EchoLocError:
        return EchoLocError(
            f"sound card {_describe(self.device)}: {why}; list the devices with: python -m sounddevice"
        )

    def _check_device(self) -> None:
        """The device exists, has the channels the head needs and takes its rate (one line if not)."""
        sd = self._sd
        inputs, outputs = self.device if isinstance(self.device, tuple) else (self.device, self.device)
        fs = self.sample_rate_hz
        try:
            for kind, dev, needed in (("input", inputs, self.n_inputs), ("output", outputs, self.n_outputs)):
                info = sd.query_devices(dev, kind)
                have = int(info[f"max_{kind}_channels"])
                if have < needed:
                    plural = "s" * (have != 1)
                    raise self._device_error(
                        f"{info['name']!r} has {have} {kind} channel{plural}, the head needs {needed}"
                    )
            sd.check_input_settings(device=inputs, channels=self.n_inputs, dtype="float32", samplerate=fs)
            sd.check_output_settings(device=outputs, channels=self.n_outputs, dtype="float32", samplerate=fs)
        except EchoLocError:
            raise
        except (ValueError, sd.PortAudioError) as error:
            raise self._device_error(f"{error} (at {fs:g} Hz)") from None

    def counters(self) -> dict[str, int]:
        """The capture side's counters (:meth:`CaptureSource.counters`) and the card's breaks,
        ``xruns``: callbacks PortAudio flagged with an over- or underflow."""
        return {**super().counters(), "xruns": sum(self.xruns.values())}

    @property
    def address(self) -> str:
        return "soundcard" + ("" if self.device is None else f":{self.device}")

    # -- what a bench wants to know

    def emission(self) -> EmissionReport:
        """How the emission instant is known, as measured so far (see :class:`EmissionReport`)."""
        with self._report_lock:
            reported = self._reported_median
            stats = self._stats
            error = reported - stats.mean if self.loopback is not None and stats.n else math.nan
            return EmissionReport(
                method="latency" if self.loopback is None else "loopback",
                frames=stats.n,
                latency_samples=stats.mean if stats.n else math.nan,
                jitter_samples=stats.std,
                reported_latency_samples=reported,
                reported_error_samples=error,
                loopback_gain=self._gain,
                correlation=self._min_correlation,
                sample_rate_hz=self.sample_rate_hz,
            )

    def levels(self) -> NDArray[np.float64]:
        """The largest magnitude of a sample of each input (a fraction of full scale) in the frames cut
        since the last call."""
        with self._report_lock:
            peaks = self._peaks.copy()
            self._peaks[:] = 0.0
        return peaks

    # -- the device

    def _open(self) -> None:
        sd = self._sd
        try:
            self._stream = sd.Stream(
                samplerate=self.sample_rate_hz,
                blocksize=self.blocksize,
                device=self.device,
                channels=(self.n_inputs, self.n_outputs),
                dtype="float32",
                latency=self.suggested_latency,
                callback=self._callback,
            )
            self._stream.start()
        except (ValueError, sd.PortAudioError) as error:
            opened, self._stream = self._stream, None
            if opened is not None:  # opened but not started: give the device back
                with contextlib.suppress(Exception):
                    opened.close()
            raise self._device_error(f"cannot open it: {error}") from None

    def _close(self) -> None:
        stream, self._stream = self._stream, None
        if stream is not None:
            try:
                stream.stop()
            finally:
                stream.close()

    def _callback(self, indata: Any, outdata: Any, frames: int, time_info: Any, status: Any) -> None:
        """PortAudio's: the pulses due in this block out, the block in. No locks, no waiting,
        nothing allocated but views: the ring and its bookkeeping are preallocated, and the worker
        learns of a block from ``_n_blocks`` and ``_written``, set last."""
        try:
            start = self._written
            outdata.fill(0)
            width, period, first = len(self._drive), self.period, self.first_emission
            k = max(0, -((first + width - 1 - start) // period))  # the first emission not over by start
            while True:
                at = first + k * period
                if at >= start + frames:
                    break
                lo, hi = max(at, start), min(at + width, start + frames)
                if lo < hi:
                    outdata[lo - start : hi - start, self.output_channel] = self._drive[lo - at : hi - at]
                k += 1
            size = self._ring_size
            at_ring = start % size
            first_part = min(frames, size - at_ring)
            self._ring[at_ring : at_ring + first_part] = indata[:first_part]
            if first_part < frames:
                self._ring[: frames - first_part] = indata[first_part:frames]
            slot = self._n_blocks % _BLOCK_RING
            self._block_start[slot] = start
            self._block_frames[slot] = frames
            self._block_adc[slot] = time_info.inputBufferAdcTime
            self._block_dac[slot] = time_info.outputBufferDacTime
            self._block_now[slot] = time_info.currentTime
            self._block_flags[slot] = _status_bits(status)
            self._n_blocks += 1
            self._written = start + frames
        except Exception as error:  # said by the worker; PortAudio stops the stream
            self._callback_error = error
            raise self._sd.CallbackAbort from None

    # -- the worker

    def _run(self) -> None:
        _Cutter(self).run()


class _Cutter:
    """The worker: reads the callbacks' bookkeeping, finds each emission and cuts its frame.

    A *break* (an xrun flag, or the worker losing track) is where the distance from output to
    input samples may have changed. The breaks read but not yet reached wait in ``breaks``; the
    *stretch* is the run of samples since the last break reached. A frame is cut only from
    samples of one stretch: an emission written before the next break whose frame (or, with a
    loopback, the search for its pulse) reaches past it is in flight, and dropped.
    """

    def __init__(self, source: SoundCardSource) -> None:
        self.source = source
        self.fs = source.sample_rate_hz
        self.n = source.head.n_samples
        self.width = source._pulse.length
        self.margin = FRACTION_TAPS + 1
        self.next_block = 0  # the next callback's bookkeeping to read
        # Each callback read: its first input index, its length, its ADC time and its current time.
        self.blocks: deque[tuple[int, int, float, float]] = deque(maxlen=_BLOCK_RING)
        self.reported: deque[tuple[int, float]] = deque(maxlen=1024)  # start, dac - adc (samples)
        self.breaks: deque[int] = deque()
        self.stretch_start = 0
        self.latency: float | None = None  # the loopback's last input-minus-output distance: tracking
        self.bias: float | None = None  # measured minus reported latency, for a search after a break
        self.k = 0
        self.last_progress = time.monotonic()

    # bookkeeping

    def limit(self) -> float:
        """Where the current stretch ends: the next break read, or infinity."""
        return self.breaks[0] if self.breaks else math.inf

    def reported_latency(self, upto: int) -> float | None:
        """The stretch's latency as the driver reports it, samples: the median of the
        ``outputBufferDacTime - inputBufferAdcTime`` of its latest callbacks that began at or
        before output index ``upto`` (an emission's: fixed once its callback is read, whatever
        comes after), else ``stream.latency``'s sum."""
        limit = min(self.limit(), upto + 1)
        values = [v for start, v in self.reported if self.stretch_start <= start < limit]
        if values:
            median = statistics.median(values[-_LATENCY_HISTORY:])
            with self.source._report_lock:
                self.source._reported_median = median
            return median
        value = getattr(self.source._stream, "latency", None)
        if isinstance(value, tuple | list) and len(value) == 2 and all(v is not None for v in value):
            return float(value[0] + value[1]) * self.fs
        return None

    def scan(self, until: int) -> None:
        """Read the callbacks that started before input index ``until``: their times, and their
        flags (counted, said; a break for those after which input and output may have slipped)."""
        src = self.source
        available = src._n_blocks
        if available - self.next_block > _BLOCK_RING:
            self.lose_track(available)
        while self.next_block < available:
            slot = self.next_block % _BLOCK_RING
            start = int(src._block_start[slot])
            if start >= until:
                break
            frames = int(src._block_frames[slot])
            adc, dac = float(src._block_adc[slot]), float(src._block_dac[slot])
            now = float(src._block_now[slot])
            flags = int(src._block_flags[slot])
            self.next_block += 1
            self.blocks.append((start, frames, adc, now))
            for bit, name in _FLAG_NAMES.items():
                if flags & bit:
                    src.xruns[name] += 1
                    then = "; the frames in flight are dropped" if bit & _BREAKS else ""
                    src._warnings.add(
                        name,
                        f"{src.address}: PortAudio reported an {_WHAT[name]} at input sample {start}{then}",
                    )
            if (
                flags & _BREAKS
                and start > self.stretch_start
                and (not self.breaks or start > self.breaks[-1])
            ):
                self.breaks.append(start)
            if adc > 0 and dac > adc:
                self.reported.append((start, (dac - adc) * self.fs))

    def lose_track(self, available: int) -> None:
        """The worker fell more than the bookkeeping ring behind: on from the present, a break."""
        src = self.source
        self.next_block = available - _BLOCK_RING // 2
        start = int(src._block_start[self.next_block % _BLOCK_RING])
        src._warnings.add(
            "behind", f"{src.address}: the worker fell behind the card; samples up to {start} skipped"
        )
        if start > self.stretch_start and (not self.breaks or start > self.breaks[-1]):
            self.breaks.append(start)

    def enter(self, start: int) -> None:
        """Go on in the stretch that a break at input index ``start`` begins: the loopback's pulse
        is looked for afresh, the emission's statistics start again."""
        self.stretch_start = start
        self.latency = None
        with self.source._report_lock:
            self.source._stats = _Welford()

    # the loop

    def wait(self, needed: int) -> bool:
        """Wait until input index ``needed`` has arrived; False if stopping."""
        src = self.source
        while src._written < needed:
            if src._stop.is_set():
                return False
            if src._callback_error is not None:
                raise EchoLocError(f"the stream's callback failed: {src._callback_error}")
            stream = src._stream
            if time.monotonic() - self.last_progress > 2.0 and stream is not None and not stream.active:
                raise EchoLocError("the sound card's stream stopped")
            before = src._written
            src._stop.wait(_POLL_S)
            if src._written != before:
                self.last_progress = time.monotonic()
        return True

    def run(self) -> None:
        src = self.source
        while not src._stop.is_set():
            if not self.frame():
                return

    def frame(self) -> bool:
        """Cut, drop or look again for frame ``self.k``; False when stopping."""
        src = self.source
        k = self.k
        out = src.first_emission + k * src.period
        while self.breaks and self.breaks[0] <= out:  # emitted after a break: in its stretch
            self.enter(self.breaks.popleft())
        plan = self.plan(k, out)
        if plan is None:  # nothing known yet about the latency: wait for callbacks
            if not self.wait(src._written + 1):
                return False
            self.scan(src._written)
            return True
        lo, hi, first = plan
        end = math.ceil(hi) + max(self.width, self.n + self.margin) + 1
        limit = self.limit()
        if not self.wait(end if math.isinf(limit) else min(end, int(limit))):
            return False
        self.scan(end)
        if self.limit() != limit or (src.loopback is None and self.plan(k, out) != plan):
            return True  # a break, or the driver's latency moved: planned again
        if math.floor(lo) - self.margin < src._written - src._ring_size + 1:
            return self.drop(k, "behind")
        # Only samples before the next break: beyond it input and output may have slipped.
        found = self.locate(k, out, lo, min(hi, limit - self.width - 1), first)
        if found is None:
            return True  # looked for again (a wider search), or dropped
        emission, correlation = found
        if emission + self.n + self.margin > limit:
            return self.drop(k, "in flight")
        frame = self.cut(emission)
        if math.floor(emission) - self.margin < src._written - src._ring_size + 1:  # overwritten meanwhile
            return self.drop(k, "behind")
        time_s = self.time_at(emission)
        src.emissions.append(Emission(k, out, emission, time_s, correlation))
        peaks = np.max(np.abs(frame), axis=1)
        with src._report_lock:
            src._stats.add(emission - out)
            np.maximum(src._peaks, peaks, out=src._peaks)
        clipped = np.flatnonzero(peaks >= CLIP_LEVEL)
        if len(clipped):
            inputs = ", ".join(map(str, clipped))
            src._warnings.add("clip", f"{src.address}: input {inputs} clips in frame {k}: lower its gain")
        src._deliver(self.counts(frame), time_s, sequence=k & 0xFFFFFFFF)
        self.k += 1
        return True

    def drop(self, k: int, why: str) -> bool:
        """Frame ``k`` is not cut (the gap it leaves in the numbering counts it lost)."""
        if why == "behind":
            src = self.source
            src._warnings.add("behind", f"{src.address}: the worker fell behind the card; frame {k} dropped")
        self.k += 1
        return True

    def plan(self, k: int, out: int) -> tuple[float, float, bool] | None:
        """Where emission ``k`` (written at output index ``out``) is to be looked for: the input
        indices (lo, hi) of the lags searched, and whether the earliest pulse is wanted (else the
        strongest); without a loopback, the emission itself (lo == hi). None: no latency known yet."""
        src = self.source
        reported = self.reported_latency(out)
        if src.loopback is None:
            return None if reported is None else (out + reported, out + reported, False)
        if self.latency is not None:  # tracking
            centre = out + self.latency
            return centre - src.track, centre + src.track, False
        if k == 0 or (reported is None and self.bias is None):
            # Nothing emitted before emission 0: the first pulse after it is its own.
            return out, out + src.max_latency, True
        # After a break or a lost pulse: half a period around where the driver's latency puts it,
        # corrected by what the loopback measured against the driver before.
        guess = out + (reported or 0.0) + (self.bias or 0.0)
        return max(guess - src.period / 2, out), guess + src.period / 2, False

    def locate(self, k: int, out: int, lo: float, hi: float, first: bool) -> tuple[float, float] | None:
        """The input index of emission ``k`` and the loopback's correlation with the pulse (NaN
        without a loopback). None: look again (the pulse left the tracking window: the next plan
        searches half a period), or the frame was dropped (no pulse: ``self.k`` moved on)."""
        src = self.source
        if src.loopback is None:
            return lo, math.nan
        if hi < lo:  # the search would reach past a break: in flight
            self.drop(k, "in flight")
            return None
        start = math.floor(lo)
        x = self.read(start, math.ceil(hi) + self.width)[src.loopback].astype(np.float64)
        found = src._pulse.find(x, first=first, min_correlation=LOOPBACK_MIN_CORRELATION)
        tracking = self.latency is not None
        if tracking and (found is None or abs(start + found[0] - (lo + hi) / 2) > src.track - 1):
            self.latency = None  # lost, or at the window's edge (it may lie beyond): search wider
            return None
        if found is None:
            if hi + self.width + 1 < self.limit():  # (else it may lie past the break: in flight)
                src._warnings.add(
                    "loopback",
                    f"{src.address}: no pulse on loopback input {src.loopback} for emission {k} "
                    "(check its wiring and level: docs/SOUNDCARD.md); frame dropped",
                )
            self.drop(k, "no pulse")
            return None
        lag, gain, correlation = found
        emission = start + lag
        self.latency = emission - out
        reported = self.reported_latency(out)
        if reported is not None:
            self.bias = self.latency - reported
        with src._report_lock:
            src._gain = gain
            src._min_correlation = (
                correlation if math.isnan(src._min_correlation) else min(src._min_correlation, correlation)
            )
        return emission, correlation

    def read(self, start: int, stop: int) -> NDArray[np.float32]:
        """Input samples ``[start, stop)``, (n_inputs, stop - start), copied out of the ring."""
        src = self.source
        size = src._ring_size
        if start < 0:
            raise EchoLocError(f"input index {start} before the stream's start")
        a, b = start % size, stop % size
        if stop - start <= size - a:
            block = src._ring[a : a + stop - start]
        else:
            block = np.concatenate((src._ring[a:], src._ring[:b]))
        return np.ascontiguousarray(block.T)

    def cut(self, emission: float) -> NDArray[np.float64]:
        """The frame starting at input index ``emission`` (fractional), (n_inputs, n_samples)."""
        whole = round(emission)
        fraction = emission - whole
        if abs(fraction) < EXACT_FRACTION:
            return self.read(whole, whole + self.n).astype(np.float64)
        half = FRACTION_TAPS
        stretch = self.read(whole - half, whole + self.n + half).astype(np.float64)
        taps = _fraction_taps(fraction)
        return np.asarray(scipy.signal.oaconvolve(stretch, taps[None, ::-1], mode="valid", axes=1))

    def time_at(self, emission: float) -> float:
        """The stream time of input index ``emission``: its callback's ADC time plus the samples
        since that callback's first (its current time less the input latency when the host API
        gives no ADC time, as some ALSA devices do)."""
        whole = math.floor(emission)
        for start, _, adc, now in reversed(self.blocks):
            if start <= whole:
                if adc > 0:
                    return adc + (emission - start) / self.fs
                value = getattr(self.source._stream, "latency", None)
                in_latency = float(value[0]) if isinstance(value, tuple | list) else 0.0
                return now - in_latency + (emission - start) / self.fs
        return math.nan

    def counts(self, frame: NDArray[np.float64]) -> NDArray[Any]:
        """Float samples (1.0: full scale) as the head's ADC counts."""
        adc = self.source.head.adc
        values = frame * adc.full_scale + adc.offset
        if adc.dtype.kind == "f":
            return values.astype(adc.dtype)
        info = np.iinfo(adc.dtype)
        return np.clip(np.rint(values), info.min, info.max).astype(adc.dtype)
