"""Calibration: the speed of sound and a fixed delay per receiver, from known targets.

The report corrects its ranges "with a reference distance" (ch. 4, tables 4.1-4.2,
"after correction"). Generalised: for frames whose reflector positions are known
(``truth_positions``), every echo's time of flight obeys

    tof_ik = L_ik / c + d_i

with ``L_ik`` the true transmitter -> reflector k -> receiver i path, ``c`` the speed
of sound and ``d_i`` a fixed delay of receiver i (electronics, transducer group
delay, trigger offset). Each true path is paired with the echo nearest its predicted
arrival, and ``(1/c, d_1..d_n)`` follow by robust (soft L1) least squares; pairing
and fit are repeated with a gate that narrows to a few times the fit's residual.

Where the targets span too narrow a range of paths to fix ``c`` to 0.5 % (1 sigma from
the fit's covariance), ``c`` stays the assumed one and only the delays are fitted.

The file written by ``echoloc calibrate`` is JSON:
``{"format": "echoloc-calibration", "version": 1, "speed_of_sound_m_s": ...,
"receiver_delays_s": [...], "echoes_used": ..., "residual_rms_s": ...}`` and, optional
(version 1 readers ignore them): ``"speed_of_sound_fitted"`` (false: kept as assumed),
``"path_sigma_m"`` (1.4826 times the median absolute path residual, m: what ``locate``
then assumes instead of its a-priori 0.5 mm), ``"echo_shape"`` (the learnt echo
envelope, :mod:`echoloc.tof.envelope_peaks`: ``name``, ``sample_rate_hz``, ``arrival_s``,
``samples``) and ``"threshold_db"`` (the detection threshold measured on the targets,
:func:`detection_threshold_db`).

**Detection threshold from the targets.** A ToF chip's envelope has no processing gain,
and how far a far target's echo stands above the clutter left by background subtraction
depends on the rig. With the targets known, calibration measures it: for each target, the
SNR of its echo on the receiver where it is the ``min_receivers``-th strongest (what an
object of ``min_receivers`` ellipsoids needs); the threshold is the level that
:data:`DETECTION_KEEP` of the targets reach, never above the estimator's default.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TypeGuard

import numpy as np
from numpy.typing import NDArray

from echoloc.errors import EchoLocError, read_text_input
from echoloc.io.recording import Recording
from echoloc.localise.locate import model_paths_m
from echoloc.tof.echoes import THRESHOLD_DB_LIMIT, ChannelEchoes, FrameEchoes
from echoloc.tof.envelope_peaks import MAD_TO_SIGMA
from echoloc.tof.templates import Template

CALIBRATION_FORMAT = "echoloc-calibration"

SPEED_FIT_MAX_RELATIVE_STD = 0.005
"""The speed of sound is fitted only where the targets determine it to 0.5 % (1 sigma, about
3 K of air temperature); else the assumed speed is kept and only the delays are fitted."""

MIN_PATH_SIGMA_M = 1e-6
"""The least path uncertainty a calibration reports, m (a noiseless simulation fits exactly)."""

MAX_SHAPE_SAMPLES = 65536
"""The most samples a calibration file's echo shape may hold."""

DETECTION_KEEP = 0.99
"""Share of the calibration targets whose echoes the measured detection threshold keeps on
enough receivers to be located (:func:`detection_threshold_db`)."""

SEARCH_THRESHOLD_DB = 0.0
"""The threshold, dB over the noise level, down to which calibration looks for the targets'
echoes before it measures the detection threshold they need."""

DETECTION_GATE_SIGMAS = 3.0
"""An echo is a target's, for :func:`detection_threshold_db`, within this many path sigmas
of the target's calibrated arrival."""

MIN_THRESHOLD_DB = -20.0
"""The lowest detection threshold a calibration file may give, dB (an echo 20 dB below the
noise level is noise)."""

MAX_CALIBRATION_FILE_BYTES = 4 << 20
"""The largest calibration file read, bytes: a full echo shape written by
:func:`write_calibration` takes about 1.6 MB."""


@dataclass(frozen=True)
class Calibration:
    """Fitted speed of sound (m/s) and per-receiver delays (s) to subtract from every tof;
    the rig's path sigma (m), learnt echo shape and measured detection threshold (dB), when
    calibration measured them."""

    speed_of_sound_m_s: float
    receiver_delays_s: tuple[float, ...]
    echoes_used: int = 0
    residual_rms_s: float = 0.0
    path_sigma_m: float | None = None
    echo_shape: Template | None = None
    speed_fitted: bool = True
    threshold_db: float | None = None


def fit_calibration(
    recording: Recording,
    echoes: Sequence[FrameEchoes],
    *,
    speed_of_sound_m_s: float,
    gate_m: float = 0.02,
    echo_shape: Template | None = None,
) -> Calibration:
    """Least-squares speed of sound and receiver delays from frames with known reflectors.

    ``echoes`` are the uncorrected echoes of frames of ``recording``; ``gate_m`` is the
    largest path difference at which an echo counts as a target's; ``echo_shape``, the
    learnt shape the echoes were timed with, is kept with the result. ``path_sigma_m`` is
    1.4826 times the median absolute path residual (at least :data:`MIN_PATH_SIGMA_M`).
    """
    if recording.truth_positions_m is None:
        raise EchoLocError(f"{recording.source}: calibration needs truth_positions")
    n_rx = recording.n_receivers
    slowness, delays = 1.0 / speed_of_sound_m_s, np.zeros(n_rx)
    # The first pairing allows for the speed of sound being off by 5 %; each pass then
    # narrows the gate to a few times the residual of the previous fit.
    relative_gate, absolute_gate_m = 0.05, gate_m
    rows: list[tuple[float, int, float]] = []
    for _ in range(8):
        rows = []
        for frame, paths in _known_paths_m(recording, echoes):
            for i, channel in enumerate(frame.channels):
                if len(channel.tof_s) == 0:
                    continue
                predicted = paths[:, i] * slowness + delays[i]
                gap = np.abs(channel.tof_s[None, :] - predicted[:, None])
                nearest = np.argmin(gap, axis=1)
                for k, j in enumerate(nearest):
                    allowed = relative_gate * paths[k, i] + absolute_gate_m
                    if gap[k, j] / slowness <= allowed:
                        rows.append((float(paths[k, i]), i, float(channel.tof_s[j])))
        seen = {i for _, i, _ in rows}
        if len(rows) < n_rx + 1 or len(seen) < n_rx:
            raise EchoLocError(
                f"{recording.source}: too few echoes match the known targets to calibrate "
                f"({len(rows)} echoes on {len(seen)} of {n_rx} receivers)"
            )
        design = np.zeros((len(rows), n_rx + 1))
        observed = np.empty(len(rows))
        for r, (path, i, tof) in enumerate(rows):
            design[r, 0] = path
            design[r, 1 + i] = 1.0
            observed[r] = tof
        # Robust (soft L1) least squares: a wrongly paired echo does not drag the fit.
        from scipy import optimize  # here, not at the top: locate needs none of its 0.4 s import

        start = np.concatenate([[slowness], delays])
        fit = optimize.least_squares(
            lambda x, a=design, b=observed: a @ x - b,
            start,
            loss="soft_l1",
            f_scale=1e-6,
            x_scale=np.abs(start) + 1e-6,
        )
        solution = fit.x
        slowness, delays = float(solution[0]), np.asarray(solution[1:], dtype=float)
        if not slowness > 0:
            raise EchoLocError(f"{recording.source}: the targets do not determine a speed of sound")
        spread_m = float(np.median(np.abs(design @ solution - observed))) / slowness
        relative_gate, absolute_gate_m = 0.0, max(5 * spread_m, 1e-3)
    residual = observed - design @ solution
    # Targets spread over too narrow a range of paths leave the speed of sound undetermined
    # (it trades with the delays): then it stays the assumed one and only the delays are fitted.
    spread_s = MAD_TO_SIGMA * float(np.median(np.abs(residual)))
    normal = design.T @ design
    if np.linalg.cond(normal) < 1e15:
        slowness_std = spread_s * math.sqrt(float(np.linalg.inv(normal)[0, 0]))
    else:
        slowness_std = math.inf
    speed_fitted = slowness_std <= SPEED_FIT_MAX_RELATIVE_STD * slowness
    if not speed_fitted:
        slowness = 1.0 / speed_of_sound_m_s
        delays = np.array(
            [
                float(np.median((observed - slowness * design[:, 0])[design[:, 1 + i] > 0]))
                for i in range(n_rx)
            ]
        )
        solution = np.concatenate([[slowness], delays])
        residual = observed - design @ solution
    # The path error of this rig, robustly (the MAD's consistency factor for Gaussian
    # errors): what the association's gate and the covariance should assume.
    path_sigma_m = MAD_TO_SIGMA * float(np.median(np.abs(residual))) / slowness
    return Calibration(
        speed_of_sound_m_s=1.0 / slowness,
        receiver_delays_s=tuple(float(d) for d in delays),
        echoes_used=len(rows),
        residual_rms_s=float(np.sqrt(np.mean(residual**2))),
        path_sigma_m=max(path_sigma_m, MIN_PATH_SIGMA_M),
        echo_shape=echo_shape,
        speed_fitted=bool(speed_fitted),
    )


def _known_paths_m(
    recording: Recording, echoes: Sequence[FrameEchoes]
) -> Iterator[tuple[FrameEchoes, NDArray[np.float64]]]:
    """Each frame of ``echoes`` that has known targets, with their true paths (n_targets, n_rx), m."""
    truth = recording.truth_positions_m
    assert truth is not None  # the callers refuse a recording without truth_positions
    for frame in echoes:
        points = truth[frame.frame]
        points = points[np.all(np.isfinite(points), axis=1)]
        if len(points) == 0:
            continue
        tx = 0 if recording.frame_transmitter is None else int(recording.frame_transmitter[frame.frame])
        yield frame, model_paths_m(recording.transmitters_m[tx], recording.receivers_m, points)


def detection_threshold_db(
    recording: Recording,
    echoes: Sequence[FrameEchoes],
    calibration: Calibration,
    *,
    ceiling_db: float,
    min_receivers: int = 3,
    keep: float = DETECTION_KEEP,
) -> float | None:
    """The detection threshold, dB, that keeps ``keep`` of the known targets locatable.

    ``echoes`` are the uncorrected echoes of frames of ``recording``, found with a threshold
    below any that this may return. For each known target, each receiver's strongest echo
    within :data:`DETECTION_GATE_SIGMAS` path sigmas of its calibrated arrival counts; the
    target needs the ``min_receivers``-th largest of those SNRs (dB). The result is the
    ``1 - keep`` quantile of what the targets need (the lower sample: at least ``keep`` of
    them reach it), at most ``ceiling_db``; None when fewer than ``min_receivers`` receivers
    or no target has echoes on ``min_receivers`` receivers.
    """
    if recording.truth_positions_m is None or recording.n_receivers < min_receivers:
        return None
    slowness = 1.0 / calibration.speed_of_sound_m_s
    gate_s = DETECTION_GATE_SIGMAS * (calibration.path_sigma_m or MIN_PATH_SIGMA_M) * slowness
    delays = np.asarray(calibration.receiver_delays_s)
    needed: list[float] = []
    for frame, paths_m in _known_paths_m(recording, echoes):
        arrivals = paths_m * slowness + delays
        for k in range(len(paths_m)):
            snr = np.full(recording.n_receivers, -np.inf)
            for i, channel in enumerate(frame.channels):
                inside = np.abs(np.asarray(channel.tof_s) - arrivals[k, i]) <= gate_s
                if inside.any():
                    # The strongest in the gate: a weak noise peak nearer the arrival does not
                    # hide the target's echo, which any threshold up to its SNR keeps.
                    snr[i] = float(np.max(np.asarray(channel.snr_db)[inside]))
            needed.append(float(np.sort(snr)[::-1][min_receivers - 1]))
    reachable = np.array([n for n in needed if math.isfinite(n)])
    if len(reachable) == 0:
        return None
    level = float(np.quantile(reachable, 1.0 - keep, method="lower"))
    return max(min(level, ceiling_db), MIN_THRESHOLD_DB)


def apply_calibration(echoes: FrameEchoes, calibration: Calibration) -> FrameEchoes:
    """The frame's echoes with each receiver's delay removed and the calibrated speed of sound."""
    channels = tuple(
        ChannelEchoes(channel.tof_s - delay, channel.amplitude, channel.snr_db)
        for channel, delay in zip(echoes.channels, calibration.receiver_delays_s, strict=True)
    )
    return replace(echoes, channels=channels, speed_of_sound_m_s=calibration.speed_of_sound_m_s)


CALIBRATION_KEYS = frozenset(
    {
        "format",
        "version",
        "speed_of_sound_m_s",
        "receiver_delays_s",
        "echoes_used",
        "residual_rms_s",
        "speed_of_sound_fitted",
        "path_sigma_m",
        "echo_shape",
        "threshold_db",
    }
)
"""The fields :func:`write_calibration` writes and :func:`read_calibration` knows."""


MAX_PATH_SIGMA_M = 1.0
"""The largest path uncertainty a calibration may give, m: beyond a metre it locates
nothing, and 1e300 m overflowed the locator's gates."""


class CalibrationWarning(UserWarning):
    """A calibration file was read, with something in it skipped."""


def write_calibration(calibration: Calibration, path: str | os.PathLike[str]) -> Path:
    """Write the calibration JSON (see the module docstring)."""
    target = Path(path)
    record: dict[str, object] = {
        "format": CALIBRATION_FORMAT,
        "version": 1,
        "speed_of_sound_m_s": calibration.speed_of_sound_m_s,
        "receiver_delays_s": list(calibration.receiver_delays_s),
        "echoes_used": calibration.echoes_used,
        "residual_rms_s": calibration.residual_rms_s,
        "speed_of_sound_fitted": calibration.speed_fitted,
    }
    if calibration.path_sigma_m is not None:
        record["path_sigma_m"] = calibration.path_sigma_m
    shape = calibration.echo_shape
    if shape is not None:
        record["echo_shape"] = {
            "name": shape.name,
            "sample_rate_hz": shape.sample_rate_hz,
            "arrival_s": shape.arrival_s,
            "samples": [float(v) for v in shape.samples],
        }
    if calibration.threshold_db is not None:
        record["threshold_db"] = calibration.threshold_db
    try:
        target.write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    except OSError as error:
        raise EchoLocError(f"{target}: cannot write calibration ({error.strerror})") from None
    return target


def read_calibration(path: str | os.PathLike[str], n_receivers: int | None = None) -> Calibration:
    """Read and check a calibration file; ``n_receivers`` must match when given."""
    source = Path(path)
    text = read_text_input(source, what="calibration file", max_bytes=MAX_CALIBRATION_FILE_BYTES)
    try:
        record = json.loads(text)
    except RecursionError:  # arrays nested 3000 deep
        raise EchoLocError(f"{source}: not a calibration file (JSON nested too deeply)") from None
    except ValueError as error:  # JSONDecodeError, and a number of more than 4300 digits
        raise EchoLocError(f"{source}: not a calibration file ({error})") from None
    if not isinstance(record, dict) or record.get("format") != CALIBRATION_FORMAT:
        raise EchoLocError(f"{source}: format is not {CALIBRATION_FORMAT!r}")
    version = record.get("version")
    unknown = sorted(str(key)[:40] for key in record if key not in CALIBRATION_KEYS)
    if unknown:  # a later echoloc may add optional fields: read on, but say what is skipped
        warnings.warn(
            f"{source}: ignoring unknown calibration field(s) {', '.join(unknown[:5])}"
            + (f" and {len(unknown) - 5} more" if len(unknown) > 5 else ""),
            CalibrationWarning,
            stacklevel=2,
        )
    if isinstance(version, bool) or version != 1:  # true == 1 in Python, not in the format
        raise EchoLocError(f"{source}: unsupported calibration version {record.get('version')!r}")
    speed = record.get("speed_of_sound_m_s")
    delays = record.get("receiver_delays_s")
    if not (_finite_number(speed) and speed > 0):
        raise EchoLocError(f"{source}: speed_of_sound_m_s must be a positive number, got {speed!r}")
    if not (isinstance(delays, list) and all(_finite_number(d) for d in delays)):
        raise EchoLocError(f"{source}: receiver_delays_s must be a list of finite numbers")
    if n_receivers is not None and len(delays) != n_receivers:
        raise EchoLocError(
            f"{source}: has delays for {len(delays)} receivers, the recording has {n_receivers}"
        )
    echoes_used = record.get("echoes_used", 0)
    whole = (isinstance(echoes_used, int) and echoes_used < 2**63) or (
        isinstance(echoes_used, float) and echoes_used.is_integer()
    )
    if not (whole and not isinstance(echoes_used, bool) and echoes_used >= 0):
        raise EchoLocError(f"{source}: echoes_used must be a whole number >= 0, got {echoes_used!r}")
    residual = record.get("residual_rms_s", 0.0)
    if not (_finite_number(residual) and residual >= 0):
        raise EchoLocError(f"{source}: residual_rms_s must be a finite number >= 0, got {residual!r}")
    path_sigma = record.get("path_sigma_m")
    if path_sigma is not None and not (_finite_number(path_sigma) and 0 < path_sigma <= MAX_PATH_SIGMA_M):
        raise EchoLocError(
            f"{source}: path_sigma_m must be a number > 0 and <= {MAX_PATH_SIGMA_M:g} m, got {path_sigma!r}"
        )
    threshold = record.get("threshold_db")
    if threshold is not None and not (
        _finite_number(threshold) and MIN_THRESHOLD_DB <= threshold <= THRESHOLD_DB_LIMIT
    ):
        raise EchoLocError(
            f"{source}: threshold_db must be a number from {MIN_THRESHOLD_DB:g} to "
            f"{THRESHOLD_DB_LIMIT:g} dB, got {threshold!r}"
        )
    speed_fitted = record.get("speed_of_sound_fitted", True)
    if not isinstance(speed_fitted, bool):
        raise EchoLocError(f"{source}: speed_of_sound_fitted must be true or false, got {speed_fitted!r}")
    return Calibration(
        speed_of_sound_m_s=float(speed),
        receiver_delays_s=tuple(float(d) for d in delays),
        echoes_used=int(echoes_used),
        residual_rms_s=float(residual),
        path_sigma_m=None if path_sigma is None else float(path_sigma),
        echo_shape=_read_shape(source, record.get("echo_shape")),
        speed_fitted=speed_fitted,
        threshold_db=None if threshold is None else float(threshold),
    )


def _finite_number(value: object) -> TypeGuard[int | float]:
    """A JSON number that is finite as a float (``true`` and ``false`` are not numbers here;
    nor is an integer too large for a float, such as 10**400)."""
    if not isinstance(value, int | float) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def _read_shape(source: Path, value: object) -> Template | None:
    """The calibration's ``echo_shape`` (optional): name, sample_rate_hz, arrival_s, samples."""
    if value is None:
        return None
    if not isinstance(value, dict):
        raise EchoLocError(f"{source}: echo_shape must be an object")
    unknown = set(value) - {"name", "sample_rate_hz", "arrival_s", "samples"}
    if unknown:
        raise EchoLocError(f"{source}: echo_shape has unknown key(s) {', '.join(sorted(unknown))}")
    samples = value.get("samples")
    if not (
        isinstance(samples, list)
        and 2 <= len(samples) <= MAX_SHAPE_SAMPLES
        and all(_finite_number(v) for v in samples)
    ):
        raise EchoLocError(
            f"{source}: echo_shape.samples must be a list of 2 to {MAX_SHAPE_SAMPLES} finite numbers"
        )
    numbers = {}
    for key in ("sample_rate_hz", "arrival_s"):
        number = value.get(key)
        if not _finite_number(number):
            raise EchoLocError(f"{source}: echo_shape.{key} must be a finite number, got {number!r}")
        numbers[key] = float(number)
    name = value.get("name", "learnt")
    if not isinstance(name, str):
        raise EchoLocError(f"{source}: echo_shape.name must be text")
    try:
        return Template(np.array(samples, dtype=float), numbers["sample_rate_hz"], numbers["arrival_s"], name)
    except EchoLocError as error:
        raise EchoLocError(f"{source}: echo_shape: {error}") from None
