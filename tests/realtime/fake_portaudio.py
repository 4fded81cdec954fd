"""A stand-in for sounddevice and the card behind it, for the sound-card source's tests.

:class:`FakeCard` has what :class:`~echoloc.realtime.soundcard_source.SoundCardSource` uses of
the sounddevice module (``Stream``, ``query_devices``, ``check_input_settings``,
``check_output_settings``, ``PortAudioError``, ``CallbackFlags``, ``CallbackAbort``), and plays
the hardware: a thread calls the stream's callback in blocks of ``block`` frames, at ``speed``
times real time, and makes each input block from what the callback wrote before:

- the "hardware" delays everything by ``latency_samples`` (+ ``fraction``) samples: DAC, the
  amplifier, the air, the microphones and the ADC. Output sample ``j`` is heard at input index
  ``j + latency + fraction + gap - dropped``: ``gap``, the output gaps so far (an output underflow
  at ``output_gap_at_block``: the DAC plays ``output_gap_samples`` of silence before that block),
  ``dropped`` the input samples lost so far (an input overflow at ``overflow_at_block``: the ADC's
  ``overflow_samples`` before that block never reach the callback);
- the loopback input carries the output channel's drive, so delayed, times ``loopback_gain``
  (negative: an inverting amplifier), plus ``loopback_noise`` (rms, of full scale): literally the
  samples written when ``fraction`` is 0, the written pulse delayed by an FFT's band-limited
  shift otherwise;
- the receivers' inputs carry, for the ``j``-th pulse the card finds on its output (onset: the
  first non-zero sample after a silence, less the pulse's leading zeros), frame ``j`` of
  ``frames`` (a simulated recording's receiver samples, for a pulse of peak 1; scaled by the
  pulse's peak written), starting where that pulse is heard;
- every input is the head's ADC's: quantised as ``[adc]`` says, then float32 as PortAudio gives it.

The callback times are the card's true ones, except that the input's ADC time is reported
``reported_error_samples`` early (so the reported latency, ``outputBufferDacTime -
inputBufferAdcTime``, is that much too long); ``callback_times=False`` reports 0 for both, as
some ALSA devices do (then ``stream.latency``, as wrong, is all the driver says). An overflow or
an output gap is flagged in that block's status; ``output_gap_flagged=False`` makes the gap a
silent slip: no flag, and a DAC time that does not know of it.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from echoloc.io.head import SensorHead

BASE_TIME_S = 1000.0
"""The stream clock at the first sample (PortAudio's origin is unspecified)."""
QUIET = 64
"""Zero samples on the output before a non-zero one that make it a pulse's onset."""


class PortAudioError(Exception):
    pass


class CallbackAbort(Exception):  # noqa: N818 - sounddevice's names
    pass


class CallbackStop(Exception):  # noqa: N818
    pass


class CallbackFlags:
    """sounddevice.CallbackFlags' face: the flags as attributes, true if any is set."""

    def __init__(self) -> None:
        self.input_underflow = False
        self.input_overflow = False
        self.output_underflow = False
        self.output_overflow = False
        self.priming_output = False

    def __bool__(self) -> bool:
        return any(vars(self).values())


@dataclass
class TimeInfo:
    inputBufferAdcTime: float  # noqa: N815 - PortAudio's names
    outputBufferDacTime: float  # noqa: N815
    currentTime: float  # noqa: N815


def _shifted(segment: NDArray[np.float64], shift: float) -> NDArray[np.float64]:
    """``segment`` delayed by ``shift`` samples (fractional), band-limited: the FFT's phase ramp on
    the segment padded with zeros (independent of the source's windowed sinc)."""
    n = len(segment) + 256
    spectrum = np.fft.rfft(segment, n) * np.exp(-2j * np.pi * np.fft.rfftfreq(n) * shift)
    return np.fft.irfft(spectrum, n)


class FakeCard:
    """A module-like stand-in for sounddevice with one device, and the device itself."""

    PortAudioError = PortAudioError
    CallbackAbort = CallbackAbort
    CallbackStop = CallbackStop
    CallbackFlags = CallbackFlags

    def __init__(
        self,
        head: SensorHead,
        frames: NDArray[np.float64] | None = None,
        *,
        latency_samples: int = 1200,
        fraction: float = 0.0,
        reported_error_samples: float = 0.0,
        callback_times: bool = True,
        loopback_gain: float = 0.5,
        block: int = 256,
        speed: float | None = 8.0,
        duration_s: float = 2.0,
        overflow_at_block: int | None = None,
        overflow_samples: int = 0,
        output_gap_at_block: int | None = None,
        output_gap_samples: int = 0,
        output_gap_flagged: bool = True,
        loopback_noise: float = 0.0,
        name: str = "Fake USB Audio 192k",
        max_inputs: int = 8,
        max_outputs: int = 2,
        rates: tuple[float, ...] = (48000.0, 96000.0, 192000.0),
        open_error: str | None = None,
    ) -> None:
        self.head = head
        self.frames = None if frames is None else np.asarray(frames, dtype=np.float64)
        self.latency = int(latency_samples)
        self.fraction = float(fraction)
        self.reported_error = float(reported_error_samples)
        self.callback_times = callback_times
        self.loopback_gain = loopback_gain
        self.block = block
        self.speed = speed
        self.duration_s = duration_s
        self.overflow_at_block = overflow_at_block
        self.overflow_samples = overflow_samples
        self.output_gap_at_block = output_gap_at_block
        self.output_gap_samples = output_gap_samples
        self.output_gap_flagged = output_gap_flagged
        self.loopback_noise = loopback_noise
        self.name = name
        self.max_inputs = max_inputs
        self.max_outputs = max_outputs
        self.rates = rates
        self.open_error = open_error
        scene = head.scene({"reflectors": [{"position_m": [0.0, 0.0, 1.0]}]})
        pulse = np.asarray(scene.waveform(0).samples, dtype=np.float64)
        # A pulse is placed once written whole: before the input gets to where it is heard.
        if self.latency < 2 * block + len(pulse) + 80 + overflow_samples:
            raise ValueError("the fake needs latency_samples >= 2 blocks + the pulse + 80 + overflow_samples")
        self.pulse_width = len(pulse)
        self.lead = int(np.flatnonzero(pulse.astype(np.float32))[0])
        self.pulse_peak = float(np.max(np.abs(pulse.astype(np.float32))))
        self.Stream = partial(FakeStream, self)
        self.streams: list[FakeStream] = []

    # -- the module's functions

    def _matches(self, device: Any) -> bool:
        if device is None or device == 0:
            return True
        return isinstance(device, str) and device.lower() in self.name.lower()

    def query_devices(self, device: Any = None, kind: str | None = None) -> Any:
        info = {
            "name": self.name,
            "index": 0,
            "hostapi": 0,
            "max_input_channels": self.max_inputs,
            "max_output_channels": self.max_outputs,
            "default_low_input_latency": 0.005,
            "default_low_output_latency": 0.005,
            "default_samplerate": 48000.0,
        }
        if device is None and kind is None:
            return [info]
        if not self._matches(device):
            raise ValueError(f"No {kind or 'input/output'} device matching {device!r}")
        return info

    def _check(self, device: Any, channels: int, samplerate: float, most: int) -> None:
        if not self._matches(device):
            raise ValueError(f"No device matching {device!r}")
        if channels > most:
            raise PortAudioError("Invalid number of channels [PaErrorCode -9998]")
        if samplerate not in self.rates:
            raise PortAudioError("Invalid sample rate [PaErrorCode -9997]")

    def check_input_settings(
        self, device: Any = None, channels: int = 1, dtype: Any = None, samplerate: float = 48000.0
    ) -> None:
        self._check(device, channels, samplerate, self.max_inputs)

    def check_output_settings(
        self, device: Any = None, channels: int = 1, dtype: Any = None, samplerate: float = 48000.0
    ) -> None:
        self._check(device, channels, samplerate, self.max_outputs)

    # -- the ADC

    def quantise(self, values: NDArray[np.float64]) -> NDArray[np.float32]:
        """What the head's ADC makes of ``values`` (1.0: full scale), as PortAudio's float32."""
        adc = self.head.adc
        if adc.dtype.kind == "f":
            return values.astype(np.float32)
        info = np.iinfo(adc.dtype)
        counts = np.clip(np.rint(values * adc.full_scale + adc.offset), info.min, info.max)
        return ((counts - adc.offset) / adc.full_scale).astype(np.float32)


class FakeStream:
    """A full-duplex callback stream on the fake card."""

    def __init__(
        self,
        card: FakeCard,
        *,
        samplerate: float,
        blocksize: int = 0,
        device: Any = None,
        channels: tuple[int, int],
        dtype: str = "float32",
        latency: Any = None,
        callback: Any,
        **_: Any,
    ) -> None:
        if card.open_error is not None:
            raise PortAudioError(card.open_error)
        card.check_input_settings(device, channels[0], dtype, samplerate)
        card.check_output_settings(device, channels[1], dtype, samplerate)
        assert dtype == "float32"
        self.card = card
        self.fs = float(samplerate)
        self.n_in, self.n_out = channels
        self.callback = callback
        self.block = blocksize or card.block
        head = card.head
        self.out_channel = head.output_channel
        self.loop_channel = head.loopback_channel
        self.order = list(head.channel_order)
        L, phi = card.latency, card.fraction
        self.l_in = L // 2
        self.l_out = L - self.l_in
        total = round(card.duration_s * self.fs)
        self.total = total
        extra = L + head.n_samples + 1024
        self.drive = np.zeros(total + extra)  # what the callback wrote on the output channel
        # What the input hears, by heard index (input index + dropped): the echoes, the drive.
        self.echoes = np.zeros((len(self.order), total + 2 * extra))
        self.played = np.zeros(total + 2 * extra)
        self.gap = 0  # output gaps so far
        self.reported_gap = 0  # those the driver knows of (in its DAC times)
        self.rng = np.random.default_rng(5)
        self.onsets: list[int] = []
        self._pending: list[int] = []  # onsets whose pulse is not yet written whole
        self.other_outputs_peak = 0.0
        self._last_nonzero = -(10**9)
        self.dropped = 0
        self.latency = ((card.latency // 2 + card.reported_error) / self.fs, (self.l_out + phi) / self.fs)
        """What the driver says: input latency (too long by the reported error) and output latency."""
        self.active = False
        self.closed = False
        self.callbacks = 0
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fake-portaudio", daemon=True)
        card.streams.append(self)

    @property
    def time(self) -> float:
        return BASE_TIME_S + self.callbacks * self.block / self.fs

    def start(self) -> None:
        self.active = True
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        self.active = False

    def close(self) -> None:
        self.closed = True

    # -- the hardware

    def _heard(self, onset: int) -> None:
        """A pulse written from output index ``onset``: its echoes (and, with a fractional delay, its
        loopback) where the input hears them."""
        card = self.card
        j = len(self.onsets)
        self.onsets.append(onset)
        written = self.drive[onset : onset + card.pulse_width]
        at = onset + card.latency + self.gap  # heard index
        pad = 64
        if card.fraction:
            loop = _shifted(np.concatenate((np.zeros(pad), written)), card.fraction)
            self.played[at - pad : at - pad + len(loop)] += loop
        if card.frames is None:
            return
        gain = float(np.max(np.abs(written))) / card.pulse_peak
        frame = card.frames[j % len(card.frames)]
        if gain != 1.0:
            frame = gain * frame
        if card.fraction:
            padded = np.concatenate((np.zeros((len(frame), pad)), frame), axis=1)
            shifted = np.stack([_shifted(row, card.fraction) for row in padded])
            self.echoes[:, at - pad : at - pad + shifted.shape[1]] += shifted
        else:
            self.echoes[:, at : at + frame.shape[1]] += frame

    def _input(self, start: int) -> NDArray[np.float32]:
        card, B = self.card, self.block
        heard = start + self.dropped
        values = np.zeros((self.n_in, B))
        values[self.order] = self.echoes[:, heard : heard + B]
        if self.loop_channel is not None:
            loop = card.loopback_gain * self.played[heard : heard + B]
            if card.loopback_noise:
                loop = loop + card.loopback_noise * self.rng.standard_normal(B)
            values[self.loop_channel] = loop
        return np.ascontiguousarray(card.quantise(values).T)

    def _run(self) -> None:
        card, B, fs = self.card, self.block, self.fs
        began = time.monotonic()
        start = 0
        try:
            while not self._stop.is_set() and start + B <= self.total:
                if card.speed is not None:
                    due = began + start / fs / card.speed
                    pause = due - time.monotonic()
                    if pause > 0:
                        time.sleep(pause)
                status = CallbackFlags()
                if card.overflow_at_block == self.callbacks:
                    self.dropped += card.overflow_samples
                    status.input_overflow = True
                if card.output_gap_at_block == self.callbacks:
                    self.gap += card.output_gap_samples
                    if card.output_gap_flagged:  # else a silent slip: the driver knows nothing
                        status.output_underflow = True
                        self.reported_gap += card.output_gap_samples
                indata = self._input(start)
                outdata = np.zeros((B, self.n_out), dtype=np.float32)
                phi, error = card.fraction, card.reported_error
                if card.callback_times:
                    times = TimeInfo(
                        inputBufferAdcTime=BASE_TIME_S + (start + self.dropped - self.l_in - error) / fs,
                        outputBufferDacTime=BASE_TIME_S + (start + self.l_out + phi + self.reported_gap) / fs,
                        currentTime=BASE_TIME_S + (start + self.dropped) / fs,
                    )
                else:
                    times = TimeInfo(0.0, 0.0, BASE_TIME_S + (start + self.dropped) / fs)
                self.callback(indata, outdata, B, times, status)
                self.callbacks += 1
                drive = outdata[:, self.out_channel].astype(np.float64)
                self.drive[start : start + B] = drive
                if not card.fraction:  # heard literally, the latency (and the gaps) later
                    at = start + card.latency + self.gap
                    self.played[at : at + B] = drive
                others = np.delete(outdata, self.out_channel, axis=1)
                if others.size:
                    self.other_outputs_peak = max(self.other_outputs_peak, float(np.max(np.abs(others))))
                nonzero = np.flatnonzero(drive) + start
                if len(nonzero):
                    gaps = np.diff(np.concatenate(([self._last_nonzero], nonzero)))
                    self._pending.extend(int(i) - card.lead for i in nonzero[gaps > QUIET])
                    self._last_nonzero = int(nonzero[-1])
                while self._pending and self._pending[0] + card.pulse_width <= start + B:
                    self._heard(self._pending.pop(0))
                start += B
        except (CallbackAbort, CallbackStop):
            pass
        except BaseException as error:  # a test double: said where the test can see it
            self.error = error
        finally:
            self.active = False
