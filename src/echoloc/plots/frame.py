"""Pictures of one frame: what was received, what the matched filter saw, where objects are."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from echoloc.pipeline import Chain, frame_echoes, frame_objects
from echoloc.tof.echoes import MatchedFilter


def plot_frame(chain: Chain, index: int, path: str | Path) -> Path:
    """Draw frame ``index``: signals, matched-filter envelopes with echoes, and a top view.

    Top: each receiver's samples against path length (tof times c). Middle: the
    envelope of each receiver's matched-filter output with the detected echoes.
    Bottom: the located objects (with 1-sigma error bars) and the true reflectors
    seen from above (x-z) and from the side (y-z).
    """
    recording = chain.recording
    c = chain.speed_of_sound_m_s
    echoes = frame_echoes(chain, index)
    objects = frame_objects(chain, echoes)
    path_axis_m = np.arange(recording.n_samples) / recording.sample_rate_hz * c
    figure = Figure(figsize=(11, 9), layout="constrained")
    grid = figure.add_gridspec(3, 2)
    signals = figure.add_subplot(grid[0, :])
    envelopes = figure.add_subplot(grid[1, :], sharex=signals)
    offsets = np.arange(recording.n_receivers) * 2.5 * float(np.max(np.abs(recording.frames[index])) or 1.0)
    for receiver, offset in enumerate(offsets):
        signals.plot(path_axis_m, recording.frames[index, receiver] + offset, lw=0.5, label=f"rx {receiver}")
    signals.set_ylabel("received samples (offset per receiver)")
    signals.set_title(f"Frame {index}: received signals")
    signals.legend(loc="upper right", fontsize="small")
    if recording.waveform is not None and recording.signal_kind == "rf":
        mf = MatchedFilter(
            np.asarray(recording.waveform, float), recording.n_samples, recording.sample_rate_hz
        )
        correlation = np.abs(mf.correlate(np.asarray(recording.frames[index])))
        for receiver, channel in enumerate(echoes.channels):
            line = envelopes.plot(path_axis_m, correlation[receiver], lw=0.8, label=f"rx {receiver}")[0]
            envelopes.plot(channel.tof_s * c, channel.amplitude, "v", color=line.get_color(), markersize=7)
        envelopes.set_title("Matched-filter envelope; triangles: detected echoes (path, amplitude)")
        found = np.concatenate([channel.tof_s for channel in echoes.channels]) * c
        if len(found):
            envelopes.set_xlim(max(found.min() - 0.5, 0.0), found.max() + 0.6)
    envelopes.set_xlabel("path length transmitter → reflector → receiver (m)")
    envelopes.set_ylabel("envelope (echo amplitude units)")
    truth = None
    if recording.truth_positions_m is not None:
        truth = recording.truth_positions_m[index]
        truth = truth[np.all(np.isfinite(truth), axis=1)]
    for column, (axis, name) in enumerate(((0, "x"), (1, "y"))):
        view = figure.add_subplot(grid[2, column])
        view.plot(
            recording.receivers_m[:, axis], recording.receivers_m[:, 2], "s", color="0.3", label="receivers"
        )
        view.plot(
            recording.transmitters_m[:, axis],
            recording.transmitters_m[:, 2],
            "*",
            color="k",
            ms=12,
            label="transmitter",
        )
        if truth is not None and len(truth):
            view.plot(truth[:, axis], truth[:, 2], "o", mfc="none", mec="tab:green", ms=12, label="truth")
        for k, obj in enumerate(objects.objects):
            view.errorbar(
                obj.position_m[axis],
                obj.position_m[2],
                xerr=obj.std_m[axis],
                yerr=obj.std_m[2],
                fmt="x",
                color="tab:red",
                label="located (±1σ)" if k == 0 else None,
            )
        view.set_xlabel(f"{name} (m)")
        view.set_ylabel("z, boresight (m)")
        view.set_aspect("equal", adjustable="datalim")
        view.set_title(f"{'top' if axis == 0 else 'side'} view ({name}-z)")
        view.legend(loc="lower right", fontsize="small")
    output = Path(path)
    figure.savefig(output, dpi=110)
    return output
