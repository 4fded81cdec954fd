"""Pictures of the physics a sensor designer checks before building hardware.

One function per command: :func:`plot_waveform` (``echoloc waveform --plot``),
:func:`plot_air` (``echoloc air --plot``) and :func:`plot_beam` (``echoloc beam
--plot``). Each writes one PNG and returns its path. The object-oriented matplotlib
API is used (no pyplot state), so they are safe to call from any thread.
"""

from __future__ import annotations

from pathlib import Path
from typing import cast

import numpy as np
import scipy.fft
from matplotlib.figure import Figure
from matplotlib.projections.polar import PolarAxes
from numpy.typing import NDArray

from echoloc.physics.air import absorption_db_per_m, speed_of_sound_cramer_m_s, speed_of_sound_m_s
from echoloc.physics.transducer import (
    Transducer,
    apply_response,
    array_factor,
    directivity,
    frequency_response,
)
from echoloc.physics.waveform import Waveform


def _save(figure: Figure, path: str | Path) -> Path:
    """Write ``figure`` to ``path`` (format by its extension) at 110 dpi, as every picture
    here is written, and return ``path`` as a Path (what each plot function returns)."""
    output = Path(path)
    figure.savefig(output, dpi=110)
    return output


def _db(values: NDArray[np.float64], floor_db: float = -80.0) -> NDArray[np.float64]:
    peak = float(np.max(np.abs(values))) or 1.0
    return np.asarray(np.maximum(20 * np.log10(np.maximum(np.abs(values) / peak, 1e-12)), floor_db))


def _envelope(
    x: NDArray[np.float64], template: NDArray[np.float64], oversample: int = 8
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Envelope of the correlation of x with template, band-limited on a finer grid, and lags in samples."""
    n = len(x) + len(template) - 1
    n_fft = scipy.fft.next_fast_len(n)
    spectrum = scipy.fft.fft(x, n_fft) * np.conj(scipy.fft.fft(template, n_fft))
    spectrum[n_fft // 2 + 1 :] = 0
    spectrum[1 : (n_fft + 1) // 2] *= 2
    fine = np.zeros(n_fft * oversample, dtype=complex)
    half = n_fft // 2 + 1
    fine[:half] = spectrum[:half]
    envelope = np.abs(scipy.fft.ifft(fine)) * oversample
    lags = np.arange(n_fft * oversample) / oversample
    lags = np.where(lags > n_fft / 2, lags - n_fft, lags)
    order = np.argsort(lags)
    return envelope[order], lags[order]


def plot_waveform(waveform: Waveform, path: str | Path, *, transducer: Transducer | None = None) -> Path:
    """The pulse, its spectrum and its matched-filter envelope, with and without a transducer pair."""
    fs = waveform.sample_rate_hz
    pulse = waveform.samples
    received = None
    label = ""
    if transducer is not None:
        label = f"after {transducer.name} pair"
        padded = np.concatenate([pulse, np.zeros(len(pulse))])
        received = apply_response(padded, transducer, fs)
    figure = Figure(figsize=(11, 9), layout="constrained")
    time_axis, spectrum_axis, acf_axis, zoom_axis = figure.subplots(4, 1)
    t_us = np.arange(len(pulse)) / fs * 1e6
    time_axis.plot(t_us, pulse, lw=0.8, label="emitted")
    if received is not None:
        time_axis.plot(np.arange(len(received)) / fs * 1e6, received, lw=0.8, label=label)
    time_axis.set_xlabel("time (µs)")
    time_axis.set_ylabel("amplitude")
    time_axis.set_title(
        f"{waveform.name}: {len(pulse)} samples at {fs / 1e3:g} kHz, {waveform.duration_s * 1e3:.3g} ms"
    )
    time_axis.legend(loc="upper right", fontsize="small")

    n_fft = scipy.fft.next_fast_len(16 * len(pulse))
    freqs = scipy.fft.rfftfreq(n_fft, 1 / fs)
    spectrum_axis.plot(freqs / 1e3, _db(scipy.fft.rfft(pulse, n_fft)), lw=0.8, label="emitted")
    if transducer is not None and received is not None:
        response = frequency_response(transducer, freqs, passes=2, sample_rate_hz=fs)
        spectrum_axis.plot(
            freqs / 1e3,
            20 * np.log10(np.maximum(np.abs(response), 1e-6)),
            "--",
            lw=0.8,
            label="transducer pair response",
        )
        spectrum_axis.plot(freqs / 1e3, _db(scipy.fft.rfft(received, n_fft)), lw=0.8, label="received")
    spectrum_axis.set_ylim(-60, 3)
    spectrum_axis.set_xlabel("frequency (kHz)")
    spectrum_axis.set_ylabel("dB")
    spectrum_axis.set_title("Spectrum")
    spectrum_axis.legend(loc="upper right", fontsize="small")

    envelope, lags = _envelope(pulse, pulse)
    lags_us = lags / fs * 1e6
    for axis in (acf_axis, zoom_axis):
        axis.plot(lags_us, _db(envelope), lw=0.8, label="autocorrelation (no transducer)")
        if received is not None:
            env_sent, lags_sent = _envelope(received, pulse)
            axis.plot(lags_sent / fs * 1e6, _db(env_sent), lw=0.8, label="received ⋆ SENT template")
        axis.set_ylabel("envelope (dB)")
        axis.set_ylim(-50, 3)
    acf_axis.set_xlim(-waveform.duration_s * 1.1e6, waveform.duration_s * 1.1e6)
    acf_axis.set_title("Matched-filter output envelope")
    acf_axis.legend(loc="upper right", fontsize="small")
    width_us = 3 * (waveform.chip_s or waveform.duration_s / 10) * 1e6
    zoom_axis.set_xlim(-width_us, width_us + (0 if received is None else 100))
    zoom_axis.set_xlabel("lag (µs)")
    zoom_axis.set_title("Main lobe, zoomed")
    return _save(figure, path)


def plot_air(
    path: str | Path,
    *,
    temperature_c: float,
    relative_humidity: float,
    pressure_pa: float,
    frequencies_hz: NDArray[np.float64],
) -> Path:
    """Absorption against frequency for several humidities, and speed of sound against temperature."""
    figure = Figure(figsize=(11, 5), layout="constrained")
    absorption_axis, speed_axis = figure.subplots(1, 2)
    freqs = np.geomspace(10e3, 300e3, 300)
    for humidity in sorted({0.1, 0.3, 0.5, 0.8, 1.0, relative_humidity}):
        style = "-" if humidity == relative_humidity else ":"
        absorption_axis.loglog(
            freqs / 1e3,
            absorption_db_per_m(freqs, temperature_c, humidity, pressure_pa),
            style,
            label=f"{humidity:.0%} RH",
        )
    marks = absorption_db_per_m(frequencies_hz, temperature_c, relative_humidity, pressure_pa)
    absorption_axis.plot(frequencies_hz / 1e3, marks, "ko", ms=4, label="asked")
    absorption_axis.set_xlabel("frequency (kHz)")
    absorption_axis.set_ylabel("absorption (dB/m)")
    absorption_axis.set_title(f"ISO 9613-1 absorption at {temperature_c:g} °C, {pressure_pa / 1e3:g} kPa")
    absorption_axis.grid(True, which="both", alpha=0.3)
    absorption_axis.legend(fontsize="small")
    temperatures = np.linspace(-20, 50, 141)
    speed_axis.plot(temperatures, speed_of_sound_m_s(temperatures, 0.0), label="dry, ideal gas")
    speed_axis.plot(
        temperatures,
        speed_of_sound_m_s(temperatures, relative_humidity),
        label=f"{relative_humidity:.0%} RH, ideal mixture",
    )
    cramer_t = np.linspace(0, 30, 61)
    speed_axis.plot(
        cramer_t, speed_of_sound_cramer_m_s(cramer_t, 0.0, pressure_pa), "--", label="dry, Cramer 1993"
    )
    speed_axis.plot(temperature_c, speed_of_sound_m_s(temperature_c, relative_humidity), "ko", ms=4)
    speed_axis.set_xlabel("temperature (°C)")
    speed_axis.set_ylabel("speed of sound (m/s)")
    speed_axis.set_title("Speed of sound")
    speed_axis.grid(True, alpha=0.3)
    speed_axis.legend(fontsize="small")
    return _save(figure, path)


def plot_beam(
    path: str | Path,
    *,
    transducer: Transducer,
    frequency_hz: float,
    speed_of_sound: float,
    elements: int = 1,
    spacing_m: float = 0.0,
    steer_rad: float = 0.0,
    weights: NDArray[np.float64] | None = None,
) -> Path:
    """Polar beam pattern (dB) of one transducer, and of a line array of them when ``elements > 1``."""
    theta = np.linspace(-np.pi / 2, np.pi / 2, 2001)
    element = np.abs(directivity(transducer, theta, frequency_hz, speed_of_sound))
    figure = Figure(figsize=(11, 5.5), layout="constrained")
    polar = cast(PolarAxes, figure.add_subplot(1, 2, 1, projection="polar"))
    cartesian = figure.add_subplot(1, 2, 2)
    curves = [("one transducer", element)]
    if elements > 1:
        factor = np.abs(
            array_factor(
                theta, elements, spacing_m, frequency_hz, speed_of_sound, steer_rad=steer_rad, weights=weights
            )
        )
        curves.append((f"array factor, {elements} × {spacing_m * 1e3:g} mm", factor))
        curves.append(("array of transducers", factor * element))
    for label, values in curves:
        level = _db(values, floor_db=-40.0)
        polar.plot(theta, level + 40, lw=1.0, label=label)
        cartesian.plot(np.degrees(theta), level, lw=1.0, label=label)
    polar.set_theta_zero_location("N")
    polar.set_theta_direction(-1)  # positive angles to the right, as in the other panel
    polar.set_thetamin(-90)
    polar.set_thetamax(90)
    polar.set_rticks([10, 20, 30, 40])
    polar.set_yticklabels(["-30", "-20", "-10", "0 dB"])
    polar.set_title(
        f"{transducer.name} at {frequency_hz / 1e3:g} kHz (radius {transducer.radius_m * 1e3:.2f} mm)"
    )
    cartesian.axhline(-3, color="0.5", ls=":", lw=0.8)
    cartesian.set_ylim(-40, 2)
    cartesian.set_xlabel("angle from boresight (°)")
    cartesian.set_ylabel("level (dB)")
    cartesian.set_title("Beam pattern; dotted: -3 dB")
    cartesian.grid(True, alpha=0.3)
    cartesian.legend(fontsize="small", loc="lower center")
    return _save(figure, path)
