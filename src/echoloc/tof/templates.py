"""Matched-filter templates: the emitted code (SENT), a direct path (DIRECT), or any recorded echo.

The report (ch. 4.1) correlates with three templates: SENT (the code as emitted),
DIRECT (the signal a receiver records straight from the transmitter, with no object)
and BALL (a recorded echo of a small ball). A :class:`Template` is samples at the
recording's rate plus ``arrival_s``: the time within the template at which the echo it
represents arrives. The recording's own ``waveform`` is the SENT template
(``arrival_s = 0``: its first sample is the instant of emission, docs/FORMATS.md); a
template cut from a recording gets its ``arrival_s`` from the geometry (the direct
path, or a reflector's known position) or from the user.

A matched filter with a template peaks where the echo best resembles it; ``tof_s`` is
that lag plus ``arrival_s``, so every template reports the same quantity. A template
unlike the echo (DIRECT's wide-angle path, a ball's own response) biases the delay:
calibration (:mod:`echoloc.localise.calibrate`) removes the constant part.
"""

from __future__ import annotations

import math
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from echoloc.errors import EchoLocError, RecordingError, open_input
from echoloc.io.recording import Recording

FORMAT_NAME = "echoloc-template"
FORMAT_VERSION = 1


@dataclass(frozen=True, eq=False)
class Template:
    """Samples of an echo template and where, within it, the echo arrives.

    ``samples`` at ``sample_rate_hz``; ``arrival_s`` is the time from the first sample
    to the echo's arrival (0 for SENT); ``name`` says where it came from.
    """

    samples: NDArray[np.float64]
    sample_rate_hz: float
    arrival_s: float = 0.0
    name: str = "sent"

    def __post_init__(self) -> None:
        samples = np.asarray(self.samples, dtype=float)
        if samples.ndim != 1 or len(samples) < 2:
            raise EchoLocError(f"template {self.name!r}: samples must be 1-D with >= 2 values")
        if not np.all(np.isfinite(samples)) or not np.any(samples):
            raise EchoLocError(f"template {self.name!r}: samples must be finite and not all zero")
        if not (np.isfinite(self.sample_rate_hz) and self.sample_rate_hz > 0):
            raise EchoLocError(
                f"template {self.name!r}: sample_rate_hz must be > 0, got {self.sample_rate_hz}"
            )
        if not np.isfinite(self.arrival_s):
            raise EchoLocError(f"template {self.name!r}: arrival_s must be finite, got {self.arrival_s}")
        object.__setattr__(self, "samples", samples)


def sent_template(recording: Recording) -> Template:
    """The recording's own ``waveform``: the emitted pulse as an ideal echo returns it."""
    if recording.waveform is None:
        raise EchoLocError(f"{recording.source}: the recording has no waveform (SENT template)")
    if not np.any(recording.waveform):
        raise EchoLocError(f"{recording.source}: waveform is all zero: no SENT template (try --template)")
    return Template(np.asarray(recording.waveform, float), recording.sample_rate_hz, 0.0, "sent")


Arrival = Literal["direct", "truth"] | float


def arrival_time_s(
    recording: Recording, frame: int, receiver: int, arrival: Arrival, speed_of_sound_m_s: float
) -> float:
    """When the echo to cut arrives at ``receiver`` in ``frame``, s.

    ``"direct"``: the straight path from the frame's transmitter; ``"truth"``: the
    shortest transmitter-reflector-receiver path among the frame's ``truth_positions``
    (exact for a point reflector; for a sphere the truth point is its surface nearest
    the transmitter, a little off the bistatic specular path); a number: that time.
    """
    if not isinstance(arrival, str):
        if not (math.isfinite(arrival) and arrival >= 0):
            raise EchoLocError(f"arrival must be a finite time >= 0 s, got {arrival!r}")
        return float(arrival)
    tx_index = 0 if recording.frame_transmitter is None else int(recording.frame_transmitter[frame])
    tx = recording.transmitters_m[tx_index]
    rx = recording.receivers_m[receiver]
    if arrival == "direct":
        return float(np.linalg.norm(rx - tx)) / speed_of_sound_m_s
    if arrival != "truth":
        raise EchoLocError(f"arrival must be 'direct', 'truth' or a time in seconds, got {arrival!r}")
    if recording.truth_positions_m is None:
        raise EchoLocError(f"{recording.source}: arrival 'truth' needs truth_positions in the recording")
    points = recording.truth_positions_m[frame]
    points = points[np.all(np.isfinite(points), axis=1)]
    if len(points) == 0:
        raise EchoLocError(f"{recording.source}: frame {frame} has no truth position to time the echo by")
    paths = np.linalg.norm(points - tx, axis=1) + np.linalg.norm(points - rx, axis=1)
    return float(paths.min()) / speed_of_sound_m_s


def cut_template(
    recording: Recording,
    *,
    receiver: int,
    frames: range,
    arrival: Arrival,
    speed_of_sound_m_s: float,
    start_s: float | None = None,
    stop_s: float | None = None,
    name: str | None = None,
) -> Template:
    """A template cut from ``frames`` of one receiver, averaged over them (noise falls as 1/sqrt(n)).

    The window defaults to 50 µs before the first frame's arrival until the SENT
    template's length plus 100 µs after it. Each frame is aligned on its own arrival
    (to the nearest sample), so a moving reflector does not smear the average.
    """
    if recording.signal_kind != "rf":
        raise EchoLocError(
            f"{recording.source}: templates are cut from rf recordings, not {recording.signal_kind!r}"
        )
    if not 0 <= receiver < recording.n_receivers:
        raise EchoLocError(
            f"{recording.source}: receiver {receiver} is not in 0..{recording.n_receivers - 1}"
        )
    if len(frames) == 0 or frames.start < 0 or frames[-1] >= recording.n_frames:
        raise EchoLocError(f"{recording.source}: frames must lie in 0..{recording.n_frames - 1}")
    fs = recording.sample_rate_hz
    first = arrival_time_s(recording, frames[0], receiver, arrival, speed_of_sound_m_s)
    length_s = (len(recording.waveform) / fs if recording.waveform is not None else 1e-3) + 100e-6
    start = first - 50e-6 if start_s is None else start_s
    stop = first + length_s if stop_s is None else stop_s
    lo, hi = int(np.floor(start * fs)), int(np.ceil(stop * fs))
    if not 0 <= lo < hi <= recording.n_samples:
        raise EchoLocError(
            f"{recording.source}: template window {start * 1e3:.3f}-{stop * 1e3:.3f} ms "
            "is not inside the frame"
        )
    cuts = []
    for frame in frames:
        shift = round((arrival_time_s(recording, frame, receiver, arrival, speed_of_sound_m_s) - first) * fs)
        a, b = lo + shift, hi + shift
        if a >= 0 and b <= recording.n_samples:
            cuts.append(np.asarray(recording.frames[frame, receiver, a:b], dtype=float))
    if not cuts:
        raise EchoLocError(f"{recording.source}: the template window leaves every selected frame")
    label = name or (arrival if isinstance(arrival, str) else "echo")
    average = np.mean(cuts, axis=0)
    if not np.any(average):
        raise EchoLocError(
            f"{recording.source}: receiver {receiver} is all zero in the template window (a dead receiver?)"
        )
    return Template(average, fs, first - lo / fs, str(label))


def write_template(template: Template, path: str | os.PathLike[str]) -> Path:
    """Write ``template`` as a NumPy ``.npz`` (format "echoloc-template", version 1)."""
    target = Path(path)
    if target.suffix != ".npz":
        raise EchoLocError(f"{target}: a template file must end in .npz")
    with open(target, "wb") as handle:
        np.savez(
            handle,
            format=FORMAT_NAME,
            version=FORMAT_VERSION,
            samples=template.samples,
            sample_rate_hz=template.sample_rate_hz,
            arrival_s=template.arrival_s,
            name=template.name,
        )
    return target


MAX_TEMPLATE_BYTES = 64 << 20
"""The most a template file may hold, on disk and unpacked, bytes: a template is one
pulse of at most :data:`echoloc.physics.waveform.MAX_WAVEFORM_SAMPLES` samples (8 MiB as float64)."""


def read_template(path: str | os.PathLike[str]) -> Template:
    """Read a template written by :func:`write_template`, checking every field.

    Only a regular file of at most :data:`MAX_TEMPLATE_BYTES` is read, and only when its
    members unpack to at most that much together (a small zip can unpack to gigabytes).
    """
    source = Path(path)
    with open_input(source, what="template file", max_bytes=MAX_TEMPLATE_BYTES, error=RecordingError) as fh:
        try:
            data = np.load(fh, allow_pickle=False)
            if not isinstance(data, np.lib.npyio.NpzFile) or data.zip is None:
                raise ValueError("a single array, not an .npz")
            with data:
                unpacked = sum(int(info.file_size) for info in data.zip.infolist())
                if unpacked > MAX_TEMPLATE_BYTES:
                    raise RecordingError(
                        f"{source}: template file unpacks to {unpacked} bytes, more than the "
                        f"{MAX_TEMPLATE_BYTES} it may hold"
                    )
                fields = {key: data[key] for key in data.files}
        except RecordingError:
            raise
        except (OSError, ValueError, EOFError, zipfile.BadZipFile):
            # numpy's own message may suggest allow_pickle=True: never for a file of unknown origin.
            raise RecordingError(
                f"{source}: not a template file (an .npz written by echoloc template)"
            ) from None
    if str(fields.get("format", "")) != FORMAT_NAME or int(fields.get("version", 0)) != FORMAT_VERSION:
        raise RecordingError(f"{source}: not an {FORMAT_NAME} version {FORMAT_VERSION} file")
    missing = [key for key in ("samples", "sample_rate_hz", "arrival_s") if key not in fields]
    if missing:
        raise RecordingError(f"{source}: template file lacks {', '.join(missing)}")
    try:
        return Template(
            np.asarray(fields["samples"], dtype=float),
            float(fields["sample_rate_hz"]),
            float(fields["arrival_s"]),
            str(fields.get("name", source.stem)),
        )
    except (EchoLocError, TypeError, ValueError) as error:
        raise RecordingError(f"{source}: {error}") from None
