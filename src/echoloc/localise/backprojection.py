"""Back-projection ("points to peaks"): a workspace grid scored by every receiver's envelope.

The report (ch. 3.5, docs/METHOD.md) names two ways to locate several reflectors. The
association of :mod:`echoloc.localise.locate` combines echoes ("peaks to points"). Here every
point ``p`` of a workspace grid looks up its path ``l_i(p) = |p - T_i| + |p - R_i|``
on every channel i (one transmitter-receiver pair) and reads that channel's
envelope there ("points to peaks"):

- :class:`Grid` and :func:`path_table`: the voxels and, per voxel and channel, the
  path in sample units (``l f_s / c``) as 16-bit fixed point (1/16 sample, 0.1 mm
  of path at 200 kHz), computed once per geometry; and a pyramid of coarser cells,
  each holding per channel the interval of samples its fine voxels read.
- :func:`channel_signals`: per channel the analytic matched-filter output (``rf``;
  :class:`echoloc.tof.echoes.MatchedFilter`) or the magnitudes (``envelope``, ``iq``),
  divided by the noise's standard deviation (:func:`echoloc.tof.echoes.noise_power`), so
  every channel weighs the same and the envelope reads as an amplitude SNR. For rf
  the output is CLEAN-restored by default (:meth:`EchoModel.restore`): the echoes
  :mod:`echoloc.tof.echoes` finds keep their main lobes and lose their code sidelobes
  (1/13 of the echo for Barker-13, far above the threshold for strong echoes), the
  residual is kept, so a missed echo still shows.
- The image is the k-th largest of the channels' envelopes at each voxel (k =
  ``min_support``): a voxel is bright only when k channels all show an echo at its
  paths. A plain sum would light up wherever two or three ellipsoids cross (ghosts).
  In 3-D, three ellipsoids always cross at points, so k = 4 (D + 1) is the default
  that makes ghosts need a coincidence; 2-D needs 3.
- :func:`search`: coarse-to-fine that cannot miss a peak. A coarse cell's score is
  the k-th largest of each channel's envelope maximised over the samples the cell's
  voxels read (a range-maximum query on a sparse table); every order statistic is
  monotone in its arguments, so this bounds every fine voxel inside the cell, and
  cells whose bound is below the threshold are never refined. The voxels it returns
  are exactly those of the full grid at or above the threshold.
- :func:`locate_channels`: every local maximum of the image above the threshold is
  a candidate; its path on each channel is read off the echo nearest the voxel's
  path (sub-sample delay); the candidates' paths go, all at once, to the
  Gauss-Newton of :func:`echoloc.localise.locate.solve_positions` (position, covariance,
  chi-square gate); candidates are accepted brightest first, each needing echoes of
  its own on D channels (an echo merged with an accepted object's may be shared).
- :func:`prepare_backprojection`, :func:`backproject_frame`, :func:`run_backprojection`:
  the per-frame calls, returning :class:`echoloc.localise.locate.FrameObjects`; several
  transmitters (fired in turn or together) are combined as extra channels.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from itertools import product

import numpy as np
import scipy.fft
from numpy.typing import NDArray
from scipy import special, stats

from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording, dead_receivers
from echoloc.localise.locate import FrameObjects, LocatedObject, LocateWarning, solve_positions
from echoloc.pipeline import Chain, frame_echoes, prepare, recording_speed_of_sound_m_s
from echoloc.tof.conditioning import Conditioning, condition_frame
from echoloc.tof.echoes import MatchedFilter, frame_time_s, noise_power

QUANTUM = 16
"""Fixed-point steps per sample of the fine path table (uint16: up to 4095 samples)."""

_FloatArray = NDArray[np.float64]
_IntArray = NDArray[np.int64]


# --- grid and lookup table -----------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Grid:
    """A box of cubic voxels; voxel ``i`` (per axis) has its centre at ``lower + (i + 1/2) voxel``.

    ``lower_m``, ``upper_m``: (D,) corners, m (D = 2 or 3); ``voxel_m``: edge, m. The box
    is covered by ``ceil((upper - lower) / voxel)`` voxels per axis.
    """

    lower_m: _FloatArray
    upper_m: _FloatArray
    voxel_m: float

    def __post_init__(self) -> None:
        lower, upper = np.asarray(self.lower_m, float), np.asarray(self.upper_m, float)
        if lower.shape != upper.shape or lower.ndim != 1 or len(lower) not in (2, 3):
            raise EchoLocError(
                f"grid: lower_m and upper_m must be 2 or 3 coordinates, got {lower} and {upper}"
            )
        if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper)) and np.all(upper > lower)):
            raise EchoLocError(f"grid: need finite upper_m > lower_m, got {lower} and {upper}")
        if not (np.isfinite(self.voxel_m) and self.voxel_m > 0):
            raise EchoLocError(f"grid: voxel_m must be > 0, got {self.voxel_m}")
        object.__setattr__(self, "lower_m", lower)
        object.__setattr__(self, "upper_m", upper)

    @property
    def dim(self) -> int:
        return len(self.lower_m)

    @cached_property
    def shape(self) -> tuple[int, ...]:
        return tuple(int(n) for n in np.ceil((self.upper_m - self.lower_m) / self.voxel_m - 1e-9))

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.shape))

    def axis_m(self, axis: int) -> _FloatArray:
        """Voxel centres along one axis, m."""
        return np.asarray(self.lower_m[axis] + (np.arange(self.shape[axis]) + 0.5) * self.voxel_m)

    def centres_m(self, flat_index: NDArray[np.integer]) -> _FloatArray:
        """Centres (n, D) of voxels given by their flat (C-order) index."""
        coords = np.stack(np.unravel_index(np.asarray(flat_index), self.shape), axis=-1)
        return np.asarray(self.lower_m + (coords + 0.5) * self.voxel_m)


@dataclass(frozen=True, eq=False)
class PathTable:
    """Per voxel and channel the path T_i -> voxel -> R_i, in samples, and its coarse pyramid.

    ``fine`` (n_voxels, n_ch) uint16 holds ``round(l f_s / c * QUANTUM)``; level L of
    ``levels`` (L = 1, 2, ...) holds for each cell of 2^L voxels per edge and each
    channel the first and last sample any of its voxels reads (n_cells, n_ch, 2),
    with ``level_shapes`` the cells per axis. Valid for one speed of sound and rate.
    """

    grid: Grid
    transmitters_m: _FloatArray  # (n_ch, D)
    receivers_m: _FloatArray  # (n_ch, D)
    sample_rate_hz: float
    speed_of_sound_m_s: float
    fine: NDArray[np.uint16]
    levels: tuple[NDArray[np.uint16], ...]
    level_shapes: tuple[tuple[int, ...], ...]

    @property
    def n_channels(self) -> int:
        return int(self.transmitters_m.shape[0])

    @property
    def n_levels(self) -> int:
        """Levels including the fine one (level 0)."""
        return len(self.levels) + 1

    @cached_property
    def max_sample(self) -> int:
        """Largest sample index any voxel reads (the envelopes are padded past it)."""
        return int(self.fine.max()) // QUANTUM + 1

    @cached_property
    def longest_span(self) -> int:
        """Most samples any coarse cell reads on one channel (sizes the range-maximum table)."""
        longest = 1
        for level in self.levels:
            longest = max(longest, int(np.max(level[..., 1].astype(np.int64) - level[..., 0])) + 1)
        return longest

    @property
    def nbytes(self) -> int:
        return int(self.fine.nbytes + sum(level.nbytes for level in self.levels))

    def paths_m(
        self, flat_index: NDArray[np.integer], channels: NDArray[np.integer] | None = None
    ) -> _FloatArray:
        """Tabulated paths of voxels (n,) on channels, m (to 1/16 sample)."""
        q = self.fine[np.asarray(flat_index)]
        if channels is not None:
            q = q[:, np.asarray(channels)]
        return np.asarray(q / QUANTUM / self.sample_rate_hz * self.speed_of_sound_m_s)


def channel_paths_m(
    transmitters_m: _FloatArray, receivers_m: _FloatArray, points_m: _FloatArray
) -> _FloatArray:
    """Closed-form paths ``|p - T_i| + |p - R_i|`` of points (n, D) on channels (n_ch, D): (n, n_ch), m."""
    points = np.asarray(points_m, float)[:, None, :]
    return np.asarray(
        np.linalg.norm(points - transmitters_m, axis=-1) + np.linalg.norm(points - receivers_m, axis=-1)
    )


def path_table(
    grid: Grid,
    transmitters_m: _FloatArray,
    receivers_m: _FloatArray,
    sample_rate_hz: float,
    speed_of_sound_m_s: float,
    *,
    top_cell_m: float = 0.08,
) -> PathTable:
    """The lookup table of one geometry: channel i is the pair (transmitters_m[i], receivers_m[i]).

    Paths are computed slab by slab (float64, then quantised) so that the peak memory
    stays near the table's own size: 2 bytes per voxel and channel (64 MB for 1 m^3 at
    5 mm and 4 channels) and about 1/4 of that for the pyramid. The pyramid goes up
    to cells no larger than ``top_cell_m``.
    """
    tx = np.atleast_2d(np.asarray(transmitters_m, float))
    rx = np.atleast_2d(np.asarray(receivers_m, float))
    if tx.shape != rx.shape or tx.shape[1] != grid.dim:
        raise EchoLocError(
            f"path table: need one transmitter and one receiver per channel in {grid.dim}-D, "
            f"got {tx.shape} and {rx.shape}"
        )
    scale = sample_rate_hz / speed_of_sound_m_s * QUANTUM
    shape = grid.shape
    n_ch = len(tx)
    fine = np.empty((*shape, n_ch), dtype=np.uint16)
    axes = [grid.axis_m(a) for a in range(grid.dim)]
    # One slab of the first axis at a time.
    rest = np.stack(np.meshgrid(*axes[1:], indexing="ij"), axis=-1)
    for i, x in enumerate(axes[0]):
        points = np.concatenate([np.full((*rest.shape[:-1], 1), x), rest], axis=-1).reshape(-1, grid.dim)
        q = np.rint(channel_paths_m(tx, rx, points) * scale)
        if q.max() > np.iinfo(np.uint16).max:
            raise EchoLocError(
                f"path table: paths up to {q.max() / scale:.2f} m exceed "
                f"{np.iinfo(np.uint16).max // QUANTUM} samples; use a smaller grid or a lower sample rate"
            )
        fine[i] = q.reshape(*shape[1:], n_ch).astype(np.uint16)
    lo = fine // QUANTUM
    hi = (fine + (QUANTUM - 1)) // QUANTUM
    levels, level_shapes = [], []
    level_lo, level_hi = lo, hi
    voxels = 1
    while voxels * 2 * grid.voxel_m <= top_cell_m * (1 + 1e-9) and max(level_lo.shape[:-1]) > 1:
        level_lo = _pool(level_lo, np.minimum)
        level_hi = _pool(level_hi, np.maximum)
        voxels *= 2
        level_shapes.append(tuple(level_lo.shape[:-1]))
        levels.append(np.stack([level_lo, level_hi], axis=-1).reshape(-1, n_ch, 2))
    return PathTable(
        grid,
        tx,
        rx,
        float(sample_rate_hz),
        float(speed_of_sound_m_s),
        fine.reshape(-1, n_ch),
        tuple(levels),
        tuple(level_shapes),
    )


def _pool(values: NDArray[np.uint16], reduce: np.ufunc) -> NDArray[np.uint16]:
    """Reduce 2 x 2 (x 2) blocks of the leading D axes; odd edges repeat their last slice."""
    dim = values.ndim - 1
    out = values
    for axis in range(dim):
        if out.shape[axis] % 2:
            out = np.concatenate([out, np.take(out, [-1], axis=axis)], axis=axis)
        a = np.take(out, np.arange(0, out.shape[axis], 2), axis=axis)
        b = np.take(out, np.arange(1, out.shape[axis], 2), axis=axis)
        out = reduce(a, b)
    return np.asarray(out)


# --- envelopes and search ------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Envelopes:
    """Per active channel the envelope in noise units and its range-maximum table.

    ``values`` (n_active, n_pad) float32 is zero past the recording; ``sparse[j]``
    holds the maximum of ``values`` over samples ``[s, s + 2^j)``.
    """

    channels: _IntArray  # indices into the path table's channels
    values: NDArray[np.float32]
    sparse: NDArray[np.float32]


def envelopes(
    channels: NDArray[np.integer],
    magnitudes: NDArray[np.floating],
    table: PathTable,
) -> Envelopes:
    """Pad magnitudes (n_active, n_samples) past the table's longest path and build the sparse table."""
    n_active, n_samples = magnitudes.shape
    n_pad = max(n_samples, table.max_sample + 2)
    values = np.zeros((n_active, n_pad), dtype=np.float32)
    values[:, :n_samples] = magnitudes
    n_j = int(np.floor(np.log2(table.longest_span))) + 1
    sparse = np.empty((n_j, n_active, n_pad), dtype=np.float32)
    sparse[0] = values
    for j in range(1, n_j):
        step = 1 << (j - 1)
        sparse[j] = sparse[j - 1]
        np.maximum(sparse[j, :, :-step], sparse[j - 1, :, step:], out=sparse[j, :, :-step])
    return Envelopes(np.asarray(channels, dtype=np.int64), values, sparse)


def _kth_largest(values: NDArray[np.floating], k: int) -> NDArray[np.float32]:
    n = values.shape[1]
    return np.asarray(np.partition(values, n - k, axis=1)[:, n - k], dtype=np.float32)


def fine_scores(
    table: PathTable, env: Envelopes, flat_index: NDArray[np.integer], k: int
) -> NDArray[np.float32]:
    """Image value at voxels: the k-th largest channel envelope, linearly interpolated at their paths."""
    q = table.fine[np.asarray(flat_index)][:, env.channels].astype(np.int64)
    i, frac = np.divmod(q, QUANTUM)
    rows = np.arange(len(env.channels))
    f = frac.astype(np.float32) / QUANTUM
    values = env.values[rows, i] * (1 - f) + env.values[rows, i + 1] * f
    return _kth_largest(values, k)


def _bounds(
    table: PathTable, env: Envelopes, level: int, cells: NDArray[np.integer], k: int
) -> NDArray[np.float32]:
    """Upper bound of the image over coarse cells of ``level`` (>= 1)."""
    spans = table.levels[level - 1][np.asarray(cells)][:, env.channels].astype(np.int64)
    lo, hi = spans[..., 0], spans[..., 1]
    j = np.floor(np.log2(hi - lo + 1)).astype(np.int64)
    rows = np.arange(len(env.channels))
    values = np.maximum(env.sparse[j, rows, lo], env.sparse[j, rows, hi - (1 << j) + 1])
    return _kth_largest(values, k)


def _children(cells: _IntArray, shape: tuple[int, ...], child_shape: tuple[int, ...]) -> _IntArray:
    coords = np.stack(np.unravel_index(cells, shape), axis=-1) * 2
    offsets = np.array(list(product((0, 1), repeat=len(shape))))
    child = (coords[:, None, :] + offsets).reshape(-1, len(shape))
    inside = np.all(child < np.array(child_shape), axis=1)
    return np.asarray(np.ravel_multi_index(tuple(child[inside].T), child_shape), dtype=np.int64)


def search(
    table: PathTable,
    env: Envelopes,
    k: int,
    floor: float,
    *,
    best_only: bool = False,
) -> tuple[_IntArray, NDArray[np.float32]]:
    """Fine voxels whose image value is >= ``floor``, found coarse to fine, and their values.

    Every cell whose upper bound reaches the floor is refined, so no voxel at or above
    it is missed. ``best_only``: only the brightest voxel is wanted, so the floor is
    raised, level by level, to the best fine value seen at the centres of the
    brightest cells (a value the maximum is at least).
    """
    top = len(table.levels)
    grid_shape = table.grid.shape
    shapes = (grid_shape, *table.level_shapes)
    cells = np.arange(int(np.prod(shapes[top])), dtype=np.int64)
    for level in range(top, 0, -1):
        bound = _bounds(table, env, level, cells, k)
        if best_only and len(cells):
            best = cells[np.argsort(bound)[-4:]]
            coords = np.stack(np.unravel_index(best, shapes[level]), axis=-1) * (1 << level) + (
                1 << (level - 1)
            )
            coords = np.minimum(coords, np.array(grid_shape) - 1)
            centre = np.ravel_multi_index(tuple(coords.T), grid_shape).astype(np.int64)
            floor = max(floor, float(fine_scores(table, env, centre, k).max()))
        cells = _children(cells[bound >= floor], shapes[level], shapes[level - 1])
    scores = fine_scores(table, env, cells, k)
    keep = scores >= floor
    return cells[keep], scores[keep]


def brute_force_image(table: PathTable, env: Envelopes, k: int, chunk: int = 1 << 20) -> NDArray[np.float32]:
    """The image at every voxel (grid.shape), the full-grid delay-and-sum baseline."""
    n = table.grid.n_voxels
    out = np.empty(n, dtype=np.float32)
    for start in range(0, n, chunk):
        index = np.arange(start, min(start + chunk, n))
        out[start : start + len(index)] = fine_scores(table, env, index, k)
    return out.reshape(table.grid.shape)


def local_maxima(shape: tuple[int, ...], flat: _IntArray, scores: NDArray[np.float32]) -> _IntArray:
    """The given voxels that no neighbour (26 in 3-D) exceeds; voxels not given count as 0.

    Scores are scattered into a zeroed grid (calloc: only touched pages cost) and
    each voxel is compared with its neighbours by flat-index offsets.
    """
    dense = np.zeros(int(np.prod(shape)), dtype=np.float32)
    dense[flat] = scores
    coords = np.stack(np.unravel_index(flat, shape), axis=-1)
    strides = np.array([int(np.prod(shape[a + 1 :])) for a in range(len(shape))])
    upper = np.array(shape) - 1
    is_max = np.ones(len(flat), dtype=bool)
    for offset in product((-1, 0, 1), repeat=len(shape)):
        if not any(offset):
            continue
        step = np.array(offset)
        inside = np.all((coords + step >= 0) & (coords + step <= upper), axis=1)
        neighbour = np.where(inside, flat + int(strides @ step), flat)
        is_max &= ~(inside & (dense[neighbour] > scores))
    return np.asarray(flat[is_max])


# --- echoes on one channel -----------------------------------------------------------


def _vertex_offset(values: NDArray[np.floating], peak: int) -> float:
    """Where the parabola through ``values[peak - 1 : peak + 2]`` peaks, relative to ``peak``
    (index units, clipped to +-0.5): the sub-sample refinement of a maximum, shared by the
    envelope and matched fits of :class:`EchoModel`. 0 at either end of ``values`` or where
    the three values do not bend down."""
    if 0 < peak < len(values) - 1:
        y0, y1, y2 = values[peak - 1], values[peak], values[peak + 1]
        denom = y0 - 2 * y1 + y2
        if denom < 0:
            return float(np.clip(0.5 * (y0 - y2) / denom, -0.5, 0.5))
    return 0.0


@dataclass(frozen=True, eq=False)
class EchoModel:
    """How one echo looks on a channel's signal, to fit and subtract it.

    ``matched`` (rf): the template's analytic autocorrelation (sub-sample table of
    :class:`echoloc.tof.echoes.MatchedFilter`), complex amplitudes. Otherwise ``shape``:
    the magnitude of the waveform's autocorrelation (envelope and iq data are
    correlated with their waveform too), its peak at index ``offset``; None when the
    recording gives no waveform (then echoes are only read, never subtracted).
    """

    matched: MatchedFilter | None = None
    shape: _FloatArray | None = None
    offset: int = 0

    @cached_property
    def rms_bandwidth_rad_per_sample(self) -> float:
        """Centred rms bandwidth of the echo's envelope, rad/sample (delay CRLB, Van Trees)."""
        if self.matched is not None:
            acf = self.matched.autocorrelation
            h = self.matched.half_width
            lags = np.arange(-h, h + 1)
            envelope = acf * np.exp(-1j * self.matched.phase_rate_rad_per_lag * lags)
            # -R''(0)/R(0) of the baseband autocorrelation = beta^2.
            curvature = np.polyfit(lags[h - 3 : h + 4], envelope.real[h - 3 : h + 4], 2)[0]
            return float(np.sqrt(max(-2 * curvature, 1e-12)))
        if self.shape is not None:
            spectrum = np.abs(np.fft.rfft(self.shape, 4 * len(self.shape))) ** 2
            omega = np.pi * np.arange(len(spectrum)) / (len(spectrum) - 1)
            return float(np.sqrt(np.sum(omega**2 * spectrum) / np.sum(spectrum)))
        return 0.5

    def fit(self, signal: NDArray[np.complexfloating], centre: float, reach: float) -> tuple[float, complex]:
        """Delay (samples) and amplitude of the echo nearest ``centre`` within ``+-reach`` samples."""
        n = len(signal)
        lo = int(max(np.floor(centre - reach), 0))
        hi = int(min(np.ceil(centre + reach), n - 1))
        if hi < lo:
            return centre, 0j
        peak = lo + int(np.argmax(np.abs(signal[lo : hi + 1])))
        if self.matched is None:
            return self._fit_envelope(np.abs(signal), peak)
        return self._fit_matched(signal, peak)

    def _fit_envelope(self, magnitude: NDArray[np.floating], peak: int) -> tuple[float, complex]:
        return peak + _vertex_offset(magnitude, peak), complex(magnitude[peak])

    def _rows(self, taus: _FloatArray) -> tuple[_IntArray, _IntArray]:
        assert self.matched is not None
        u = self.matched.oversample
        grid = np.rint(taus * u).astype(np.int64)
        base, row = np.divmod(grid, u)
        return base, row

    def _segments(self, signal: NDArray[np.complexfloating], base: _IntArray) -> NDArray[np.complex128]:
        assert self.matched is not None
        h = self.matched.half_width
        index = base[:, None] + np.arange(-h, h + 1)
        inside = (index >= 0) & (index < len(signal))
        return np.where(inside, signal[np.clip(index, 0, len(signal) - 1)], 0)

    def _fit_matched(self, signal: NDArray[np.complexfloating], peak: int) -> tuple[float, complex]:
        # Least-squares fit of a * R(m - tau) around the peak: tau maximises
        # |<R_tau, x>|^2 / <R_tau, R_tau>, searched in 1/32 sample then by a parabola.
        assert self.matched is not None
        table = self.matched.acf_table
        taus = peak + np.arange(-32, 33) / 32
        base, row = self._rows(taus)
        shapes = table[row]
        seg = self._segments(signal, base)
        num = np.sum(np.conj(shapes) * seg, axis=1)
        den = np.sum(np.abs(shapes) ** 2, axis=1)
        cost = np.abs(num) ** 2 / den
        j = int(np.argmax(cost))
        tau = float(taus[j] + _vertex_offset(cost, j) / 32)
        base1, row1 = self._rows(np.array([tau]))
        shape1 = table[row1[0]]
        seg1 = self._segments(signal, base1)[0]
        amplitude = complex(np.sum(np.conj(shape1) * seg1) / np.sum(np.abs(shape1) ** 2))
        return tau, amplitude

    @cached_property
    def beam_half_width(self) -> float:
        """Half width of the echo's main lobe to its first null (or -26 dB), samples."""
        if self.matched is not None:
            envelope = np.abs(self.matched.autocorrelation)
            centre = self.matched.half_width
        elif self.shape is not None:
            envelope, centre = self.shape / max(float(np.max(self.shape)), 1e-300), self.offset
        else:
            return 8.0
        right = centre
        while (
            right + 1 < len(envelope) and envelope[right + 1] < envelope[right] and envelope[right + 1] > 0.05
        ):
            right += 1
        return float(right - centre + 1)

    def _model(self, tau: float, beam: bool) -> tuple[NDArray[np.complex128], int]:
        """Unit echo at delay ``tau`` (samples) and the index of its first sample."""
        if self.matched is not None:
            h = self.matched.half_width
            base, row = self._rows(np.array([tau]))
            model = np.array(self.matched.acf_table[row[0]])
            if beam:
                lags = np.arange(-h, h + 1) - row[0] / self.matched.oversample
                model[np.abs(lags) > self.beam_half_width] = 0
            return model, int(base[0]) - h
        assert self.shape is not None
        frac = tau - np.floor(tau)
        grid = np.arange(len(self.shape))
        unit = np.interp(grid - frac, grid, self.shape, 0, 0) / max(float(np.max(self.shape)), 1e-300)
        return unit.astype(np.complex128), int(np.floor(tau)) - self.offset

    def subtract(
        self, signal: NDArray[np.complex128], tau: float, amplitude: complex, *, beam: bool = False
    ) -> tuple[int, int]:
        """Remove the echo (or, ``beam``, its main lobe only) in place; returns the samples touched."""
        if self.matched is None and self.shape is None:
            return 0, 0
        model, start = self._model(tau, beam)
        n = len(signal)
        lo, hi = max(start, 0), min(start + len(model), n)
        if hi > lo:
            signal[lo:hi] -= amplitude * model[lo - start : hi - start]
        return lo, hi

    def restore(
        self, signal: NDArray[np.complex128], taus: _FloatArray
    ) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
        """The signal with the echoes at ``taus`` (samples) cut to their main lobes (CLEAN's restored map).

        The echoes' complex amplitudes are fitted together by least squares; the
        residual (noise and anything the echo list missed) is kept. Returns the
        restored signal and the amplitudes.
        """
        if self.matched is None or len(taus) == 0:
            return signal.copy(), np.zeros(len(taus), dtype=complex)
        n = len(signal)
        columns = np.zeros((n, len(taus)), dtype=complex)
        for j, tau in enumerate(taus):
            model, start = self._model(float(tau), False)
            lo, hi = max(start, 0), min(start + len(model), n)
            columns[lo:hi, j] = model[lo - start : hi - start]
        amplitudes = np.asarray(np.linalg.lstsq(columns, signal, rcond=None)[0], dtype=np.complex128)
        out = np.asarray(signal - columns @ amplitudes, dtype=np.complex128)
        for tau, amplitude in zip(taus, amplitudes, strict=True):
            self.subtract(out, float(tau), -complex(amplitude), beam=True)
        return out, amplitudes


# --- objects -------------------------------------------------------------------------


@dataclass(frozen=True)
class BackprojectionOptions:
    """Options of back-projection.

    threshold_db
        An echo supports a point when its amplitude SNR (envelope over the noise's
        standard deviation) exceeds this, in dB of power (14 dB as
        :class:`echoloc.tof.echoes.EchoOptions`: amplitude 5 sigma).
    min_support
        Channels that must show an echo at a point's paths; None: D + 1 (4 in 3-D).
        The image is the min_support-th largest envelope.
    path_sigma_m
        A-priori standard deviation of every path (air, jitter), m, added in quadrature
        to the echo's delay bound ``1 / (beta sqrt(2 SNR))`` (Van Trees, delay CRLB).
    gate_probability
        Chi-square gate on the fit of the supporting channels' paths.
    max_objects
        At most this many objects per frame.
    mask_radius_m
        A candidate that solves this close to an accepted object is the same object.
    max_candidates
        At most this many local maxima of the image are tried, brightest first.
    amplitude_log_sigma
        Spread of a reflector's echo amplitudes about the spreading model (natural-log
        units, as :data:`echoloc.localise.locate.AMPLITUDE_LOG_SIGMA`): a candidate whose own
        echoes' ``|a| r_T r_R`` differ beyond the chi-square gate is rejected as a
        crossing of different reflectors. None: no amplitude check (e.g. transducers
        whose beams make the amplitudes differ).
    top_cell_m
        Edge of the coarsest cells of the pyramid, m.
    brute_force
        Search the full fine grid at every step instead of coarse to fine (baseline).
    restore
        rf recordings: image the matched-filter output with the code's sidelobes
        removed (CLEAN's restored map: each echo found by :mod:`echoloc.tof.echoes`
        reduced to its main lobe, the residual kept), and read paths off those echoes.
        False: the raw matched-filter envelopes, where a strong echo's sidelobes
        (1/13 of it for Barker-13) bias the weaker echoes' fits.
    """

    threshold_db: float = 14.0
    min_support: int | None = None
    path_sigma_m: float = 0.5e-3
    gate_probability: float = 0.999
    max_objects: int = 16
    mask_radius_m: float = 0.01
    max_candidates: int = 2000
    amplitude_log_sigma: float | None = None
    top_cell_m: float = 0.08
    brute_force: bool = False
    restore: bool = True


def _support(options: BackprojectionOptions, dim: int, n_channels: int) -> int:
    """The channels a voxel needs: ``min_support``, or by default D + 1 when there are that
    many working channels and D (the bare intersection, without the ghost test) when one is dead."""
    if options.min_support is None:
        if n_channels < dim:
            raise EchoLocError(
                f"backprojection: {n_channels} working channel(s), a {dim}-D position needs at least {dim}"
            )
        return min(dim + 1, n_channels)
    k = options.min_support
    if k < dim or k > n_channels:
        raise EchoLocError(
            f"backprojection: min_support={k} needs {dim} <= min_support <= {n_channels} working channels"
        )
    return k


Components = list[tuple[_FloatArray, NDArray[np.complex128]]]
"""Per active channel, the delays (samples) and amplitudes of its echoes restored to main lobes."""


def locate_channels(
    table: PathTable,
    signals: NDArray[np.complex128],
    channels: NDArray[np.integer],
    models: Sequence[EchoModel],
    options: BackprojectionOptions,
    *,
    components: Components | None = None,
    channel_receivers: NDArray[np.integer] | None = None,
    channel_transmitters: NDArray[np.integer] | None = None,
) -> list[LocatedObject]:
    """Objects from signals in noise units (n_active, n_samples), one per active channel.

    ``channels`` index the table's channels; ``models`` give each active channel's
    echo shape. Every local maximum of the image at or above the threshold is a
    candidate. Its path on each channel is read off the echo nearest the voxel's path:
    with ``components`` (signals restored by :meth:`EchoModel.restore`) the listed
    echo, otherwise an echo fitted on the signal. The candidates' paths are solved
    together (Gauss-Newton, chi-square gate), then accepted brightest first; each
    needs ``min(k, D)`` echoes no accepted object has used; the others may be shared
    (a merged echo: its sigma grows by the main lobe's spread).
    """
    channels = np.asarray(channels, dtype=np.int64)
    n_active = len(channels)
    dim = table.grid.dim
    k = _support(options, dim, n_active)
    threshold = 10 ** (options.threshold_db / 20)
    to_samples = table.sample_rate_hz / table.speed_of_sound_m_s
    reach = np.sqrt(dim) * table.grid.voxel_m * to_samples + 2.0
    env = envelopes(channels, np.abs(signals).astype(np.float32), table)
    if options.brute_force:
        image = brute_force_image(table, env, k).ravel()
        flat = np.flatnonzero(image >= threshold)
        scores = image[flat]
    else:
        flat, scores = search(table, env, k, threshold)
    peaks = local_maxima(table.grid.shape, flat, scores)
    if len(peaks) == 0:
        return []
    peak_scores = fine_scores(table, env, peaks, k)
    order = np.argsort(-peak_scores, kind="stable")
    peaks = peaks[order][: options.max_candidates]
    predicted = table.fine[peaks][:, channels] / QUANTUM
    tau = np.array(predicted)
    amplitude = np.zeros(tau.shape)
    for i in range(n_active):
        if components is not None:
            listed_tau, listed_amp = components[i]
            if len(listed_tau) == 0:
                continue
            gap = np.abs(listed_tau[None, :] - predicted[:, i : i + 1])
            near = gap <= reach
            strength = np.where(near, np.abs(listed_amp)[None, :], -1.0)
            pick = np.argmax(strength, axis=1)
            has = near[np.arange(len(peaks)), pick]
            tau[has, i] = listed_tau[pick[has]]
            amplitude[has, i] = np.abs(listed_amp[pick[has]])
        else:
            for row in range(len(peaks)):
                t, a = models[i].fit(signals[i], float(predicted[row, i]), reach)
                tau[row, i], amplitude[row, i] = t, abs(a)
    supported = amplitude >= threshold
    # Candidates reading the same echoes are one candidate: keep the brightest.
    key = np.where(supported, np.rint(tau * 8), -1)
    _, first = np.unique(key, axis=0, return_index=True)
    keep = np.sort(first)
    keep = keep[supported[keep].sum(axis=1) >= k]
    if len(keep) == 0:
        return []
    centres = table.grid.centres_m(peaks[keep])
    solutions = _solve_batch(
        table.transmitters_m[channels],
        table.receivers_m[channels],
        tau[keep] / to_samples,
        amplitude[keep],
        supported[keep],
        centres,
        models,
        options,
        1 / to_samples,
    )
    half_lobe = 0.5 * np.array([m.beam_half_width for m in models])
    used: list[list[float]] = [[] for _ in range(n_active)]
    objects: list[LocatedObject] = []
    active_rx = channels if channel_receivers is None else np.asarray(channel_receivers)[channels]
    active_tx = (
        np.zeros_like(channels)
        if channel_transmitters is None
        else np.asarray(channel_transmitters)[channels]
    )
    # Two passes: first the candidates whose echoes are all their own, so that a
    # crossing that borrows an object's merged echo cannot take another's first.
    taken = np.zeros(len(keep), dtype=bool)
    for allow_shared in (False, True):
        for row, candidate in enumerate(keep):
            if len(objects) >= options.max_objects or taken[row]:
                continue
            solved = solutions[row]
            support = np.flatnonzero(supported[candidate])
            shared = [i for i in support if any(abs(tau[candidate, i] - t) <= half_lobe[i] for t in used[i])]
            if len(support) - len(shared) < min(k, dim) or (shared and not allow_shared):
                continue
            if shared:
                # Re-solve with the merged echoes' wider spread.
                mask = np.zeros(n_active, dtype=bool)
                mask[shared] = True
                solved = _solve_batch(
                    table.transmitters_m[channels],
                    table.receivers_m[channels],
                    tau[candidate][None] / to_samples,
                    amplitude[candidate][None],
                    supported[candidate][None],
                    centres[row][None],
                    models,
                    options,
                    1 / to_samples,
                    shared=mask[None],
                )[0]
            if solved is None or not _inside(table.grid, solved[0]):
                continue
            if any(np.linalg.norm(o.position_m - solved[0]) <= options.mask_radius_m for o in objects):
                continue
            own = np.setdiff1d(support, shared)
            if options.amplitude_log_sigma is not None and not _amplitudes_agree(
                solved[0],
                table.transmitters_m[channels[own]],
                table.receivers_m[channels[own]],
                amplitude[candidate, own],
                options,
            ):
                continue
            taken[row] = True
            for channel in support.tolist():
                used[channel].append(float(tau[candidate, channel]))
            position, covariance, chi2, p_value = solved
            objects.append(
                LocatedObject(
                    position_m=position,
                    covariance_m2=covariance,
                    receivers=tuple(int(r) for r in active_rx[support]),
                    echo_indices=tuple(-1 for _ in support),
                    chi2=chi2,
                    score=p_value * len(support) / n_active,
                    transmitters=tuple(int(t) for t in active_tx[support]),
                    shared=len(shared),
                )
            )
    return objects


def _amplitudes_agree(
    position_m: _FloatArray,
    tx_m: _FloatArray,
    rx_m: _FloatArray,
    snr: _FloatArray,
    options: BackprojectionOptions,
) -> bool:
    """Whether one reflector explains the echoes' amplitudes: ``|a_i| r_Ti r_Ri`` equal within the gate.

    A point reflector's echo falls off as ``1 / (r_T r_R)`` (spherical spreading both
    ways), so the product is its strength on every channel; echoes of different
    reflectors (a ghost crossing) differ. Log units, sigma ``amplitude_log_sigma``
    in quadrature with the amplitude noise ``1 / SNR``.
    """
    assert options.amplitude_log_sigma is not None
    if len(snr) < 2:
        return True
    spread = np.linalg.norm(position_m - tx_m, axis=1) * np.linalg.norm(position_m - rx_m, axis=1)
    value = np.log(np.maximum(snr, 1e-12) * spread)
    weight = 1.0 / (options.amplitude_log_sigma**2 + 1.0 / np.maximum(snr, 1e-12) ** 2)
    mean = np.sum(weight * value) / np.sum(weight)
    chi2 = float(np.sum(weight * (value - mean) ** 2))
    return chi2 <= float(stats.chi2.ppf(options.gate_probability, len(snr) - 1))


def _inside(grid: Grid, point: _FloatArray) -> bool:
    margin = grid.voxel_m
    return bool(np.all(point >= grid.lower_m - margin) and np.all(point <= grid.upper_m + margin))


def _solve_batch(
    tx_m: _FloatArray,
    rx_m: _FloatArray,
    paths_m: _FloatArray,
    snr: _FloatArray,
    supported: NDArray[np.bool_],
    start_m: _FloatArray,
    models: Sequence[EchoModel],
    options: BackprojectionOptions,
    sample_m: float,
    shared: NDArray[np.bool_] | None = None,
) -> list[tuple[_FloatArray, _FloatArray, float, float] | None]:
    """Gauss-Newton on each row's supporting channels; None for rows that fail the gate.

    Path sigma: ``path_sigma_m`` in quadrature with the delay bound
    ``1 / (beta sqrt(2 SNR))`` samples (Van Trees, Part I, eq. 10.80, with beta the
    echo's rms bandwidth); a shared echo adds the main lobe's half width over sqrt 3.
    """
    dim = start_m.shape[1]
    beta = np.array([m.rms_bandwidth_rad_per_sample for m in models])
    sigma_samples = 1.0 / (beta * np.sqrt(2.0) * np.maximum(snr, 1e-12))
    sigma = np.sqrt(options.path_sigma_m**2 + (sigma_samples * sample_m) ** 2)
    if shared is not None:
        lobe = np.array([m.beam_half_width for m in models]) * sample_m
        sigma = np.where(shared, np.hypot(sigma, lobe / np.sqrt(3)), sigma)
    paths = np.where(supported, paths_m, np.nan)
    solution = solve_positions(tx_m, rx_m, paths, sigma, start_m=start_m)
    dof = supported.sum(axis=1) - dim
    gate = np.where(dof > 0, stats.chi2.ppf(options.gate_probability, np.maximum(dof, 1)), np.inf)
    ok = solution.converged & (solution.chi2 <= gate)
    p_value = np.where(dof > 0, special.chdtrc(np.maximum(dof, 1), solution.chi2), 1.0)
    return [
        (solution.position_m[r], solution.covariance_m2[r], float(solution.chi2[r]), float(p_value[r]))
        if ok[r]
        else None
        for r in range(len(paths))
    ]


# --- recordings ----------------------------------------------------------------------


def default_grid(voxel_m: float = 0.005) -> Grid:
    """The issue's workspace: the cubic metre in front of the array, x, y in +-0.5 m, z 0.2-1.2 m."""
    return Grid(np.array([-0.5, -0.5, 0.2]), np.array([0.5, 0.5, 1.2]), voxel_m)


@dataclass(frozen=True, eq=False)
class Backprojector:
    """Everything back-projection reuses for one recording: the table, filters and echo models.

    Table channel ``t * n_rx + r`` is transmitter t with receiver r.
    """

    recording: Recording
    table: PathTable
    options: BackprojectionOptions
    speed_of_sound_m_s: float
    filters: tuple[MatchedFilter | None, ...]  # per transmitter (rf)
    templates: tuple[NDArray[np.complex128] | None, ...]  # per transmitter (envelope, iq)
    models: tuple[EchoModel, ...]  # per transmitter
    usable_receivers: NDArray[np.bool_]
    conditioning: Conditioning = field(default_factory=Conditioning)
    chain: Chain | None = None  # the echo finder, for restored envelopes

    @property
    def n_receivers(self) -> int:
        return self.recording.n_receivers

    @cached_property
    def channel_transmitters(self) -> _IntArray:
        return np.repeat(np.arange(len(self.recording.transmitters_m)), self.n_receivers)

    @cached_property
    def channel_receivers(self) -> _IntArray:
        return np.tile(np.arange(self.n_receivers), len(self.recording.transmitters_m))


def check_working_receivers(
    recording: Recording, working: int, dim: int, options: BackprojectionOptions
) -> None:
    """Refuse fewer working receivers than the grid has dimensions, in one line; warn when each
    frame's working channels are exactly that many (every crossing of their paths is kept)."""
    if working < dim:
        raise EchoLocError(
            f"{recording.source}: only {working} working receiver(s), "
            f"back-projection in {dim}-D needs at least {dim}"
        )
    per_frame = len(recording.transmitters_m) if recording.firing == "simultaneous" else 1
    if options.min_support is None and working * per_frame == dim:
        warnings.warn(
            f"{recording.source}: {dim} working channels: back-projection keeps every crossing of "
            f"their {dim} paths, so ghosts of several reflectors cannot be told from them",
            LocateWarning,
            stacklevel=3,
        )


def prepare_backprojection(
    recording: Recording,
    grid: Grid | None = None,
    options: BackprojectionOptions | None = None,
    *,
    speed_of_sound_m_s: float | None = None,
    conditioning: Conditioning | None = None,
) -> Backprojector:
    """Build the path table and echo models for ``recording`` (default grid: :func:`default_grid`)."""
    grid = grid or default_grid()
    options = options or BackprojectionOptions()
    if grid.dim != recording.transmitters_m.shape[1]:
        raise EchoLocError(
            f"{recording.source}: a {grid.dim}-D grid for a recording with "
            f"{recording.transmitters_m.shape[1]}-D positions"
        )
    c = speed_of_sound_m_s or recording_speed_of_sound_m_s(recording)
    n_tx, n_rx = len(recording.transmitters_m), recording.n_receivers
    tx = np.repeat(recording.transmitters_m, n_rx, axis=0)
    rx = np.tile(recording.receivers_m, (n_tx, 1))
    table = path_table(grid, tx, rx, recording.sample_rate_hz, c, top_cell_m=options.top_cell_m)
    filters: list[MatchedFilter | None] = []
    templates: list[NDArray[np.complex128] | None] = []
    models: list[EchoModel] = []
    for t in range(n_tx):
        waveform = recording.waveform
        if recording.transmitter_waveforms is not None:
            waveform = np.asarray(recording.transmitter_waveforms[t])
        if recording.signal_kind == "rf":
            if waveform is None:
                raise EchoLocError(
                    f"{recording.source}: an rf recording needs its waveform for back-projection"
                )
            mf = MatchedFilter(np.asarray(waveform, float), recording.n_samples, recording.sample_rate_hz)
            filters.append(mf)
            templates.append(None)
            models.append(EchoModel(matched=mf))
        else:
            filters.append(None)
            if waveform is None:
                templates.append(None)
                models.append(EchoModel())
            else:
                template = np.asarray(waveform, dtype=np.complex128)
                templates.append(template)
                acf = np.abs(np.correlate(template, template, "full"))
                models.append(EchoModel(shape=acf / acf.max(), offset=len(template) - 1))
    usable = np.ones(n_rx, dtype=bool)
    usable[dead_receivers(recording)] = False
    check_working_receivers(recording, int(usable.sum()), grid.dim, options)
    conditioning = conditioning or Conditioning()
    chain = None
    if options.restore and recording.signal_kind == "rf" and recording.firing != "simultaneous":
        chain = prepare(recording, speed_of_sound_m_s=c, conditioning=conditioning)
    return Backprojector(
        recording,
        table,
        options,
        c,
        tuple(filters),
        tuple(templates),
        tuple(models),
        usable,
        conditioning,
        chain,
    )


def channel_signals(
    bp: Backprojector, index: int
) -> tuple[_IntArray, NDArray[np.complex128], Components | None]:
    """Active table channels of frame ``index``, their signals in noise units, and their echoes.

    rf: the analytic matched-filter output with the frame's transmitter's template
    (with simultaneous firing, every transmitter's); envelope and iq: the magnitudes.
    Each row is divided by ``sqrt(noise_power(row))``, the noise's robust rms. With
    ``options.restore`` (rf) the rows are CLEAN-restored (:meth:`EchoModel.restore`)
    around the echoes :mod:`echoloc.tof.echoes` finds, which are returned too.
    """
    recording = bp.recording
    frame = condition_frame(recording.frames[index], recording, bp.conditioning, index)
    if recording.firing == "simultaneous":
        transmitters = list(range(len(recording.transmitters_m)))
    else:
        transmitters = [0 if recording.frame_transmitter is None else int(recording.frame_transmitter[index])]
    rows, channels = [], []
    receivers = np.flatnonzero(bp.usable_receivers)
    echoes = None if bp.chain is None else frame_echoes(bp.chain, index)
    components: Components | None = None if echoes is None else []
    for t in transmitters:
        mf = bp.filters[t]
        if mf is not None:
            signal = mf.correlate(np.asarray(frame[receivers], float))
        else:
            signal = _baseband_correlation(
                np.asarray(frame[receivers]), bp.templates[t], recording.signal_kind
            )
        for j, r in enumerate(receivers):
            row = signal[j] / np.sqrt(noise_power(signal[j]))
            if echoes is not None and components is not None:
                taus = np.asarray(echoes.channels[r].tof_s) * recording.sample_rate_hz
                row, amplitudes = bp.models[t].restore(row, taus)
                components.append((taus, amplitudes))
            rows.append(row)
            channels.append(t * bp.n_receivers + r)
    return np.array(channels, dtype=np.int64), np.asarray(np.stack(rows), dtype=np.complex128), components


def _baseband_correlation(
    frame: NDArray[np.generic], template: NDArray[np.complex128] | None, signal_kind: str
) -> NDArray[np.complex128]:
    """Matched filter of ``iq`` samples, or of ``envelope`` magnitudes less their median, with the waveform.

    ``sum_n x[n + k] conj(w[n]) / sum |w|^2``: an echo ``a w[n - k0]`` gives ``a`` at
    ``k0``, its arrival. Without a waveform the magnitudes themselves (an echo then
    peaks where its envelope does: a calibration constant, docs/FORMATS.md).
    """
    x = np.asarray(frame, dtype=np.complex128)
    if signal_kind == "envelope":
        x = np.abs(x) - np.median(np.abs(x), axis=-1, keepdims=True)
    if template is None:
        return np.asarray(np.abs(x), dtype=np.complex128)
    n = x.shape[-1]
    n_fft = int(scipy.fft.next_fast_len(n + len(template)))
    spectrum = scipy.fft.fft(x, n_fft, axis=-1) * np.conj(scipy.fft.fft(template, n_fft))
    out = scipy.fft.ifft(spectrum, n_fft, axis=-1)[..., :n] / np.sum(np.abs(template) ** 2)
    return np.asarray(out, dtype=np.complex128)


def _locate(
    bp: Backprojector, channels: _IntArray, signals: NDArray[np.complex128], components: Components | None
) -> list[LocatedObject]:
    models = [bp.models[int(t)] for t in bp.channel_transmitters[channels]]
    return locate_channels(
        bp.table,
        signals,
        channels,
        models,
        bp.options,
        components=components,
        channel_receivers=bp.channel_receivers,
        channel_transmitters=bp.channel_transmitters,
    )


def backproject_frame(bp: Backprojector, index: int) -> FrameObjects:
    """Objects of frame ``index`` from its own channels (the same values as the association returns)."""
    channels, signals, components = channel_signals(bp, index)
    objects = _locate(bp, channels, signals, components)
    return FrameObjects(index, frame_time_s(bp.recording, index), tuple(objects))


def run_backprojection(bp: Backprojector, frames: Iterable[int] | None = None) -> Iterator[FrameObjects]:
    """Objects of every frame (or of ``frames``).

    With several transmitters fired in turn, each frame is located with the latest
    frame of every other transmitter as extra channels (as :func:`echoloc.pipeline.run`).
    """
    recording = bp.recording
    indices = range(recording.n_frames) if frames is None else frames
    combine = (
        len(recording.transmitters_m) > 1
        and recording.firing != "simultaneous"
        and recording.frame_transmitter is not None
    )
    latest: dict[int, tuple[_IntArray, NDArray[np.complex128], Components | None]] = {}
    for index in indices:
        channels, signals, components = channel_signals(bp, index)
        if combine:
            assert recording.frame_transmitter is not None
            latest[int(recording.frame_transmitter[index])] = (channels, signals, components)
            kept = [latest[t] for t in sorted(latest)]
            channels = np.concatenate([item[0] for item in kept])
            signals = np.concatenate([item[1] for item in kept])
            components = None if components is None else [c for item in kept for c in item[2] or []]
        objects = _locate(bp, channels, signals, components)
        yield FrameObjects(index, frame_time_s(recording, index), tuple(objects))


@dataclass(frozen=True, eq=False)
class Image:
    """Back-projected image on a grid: per voxel the k-th largest channel amplitude SNR."""

    grid: Grid
    values: NDArray[np.float32]
    support: int
    threshold: float


def frame_image(bp: Backprojector, index: int) -> Image:
    """The full-grid image of frame ``index`` (restored envelopes with ``options.restore``)."""
    channels, signals, _ = channel_signals(bp, index)
    k = _support(bp.options, bp.table.grid.dim, len(channels))
    env = envelopes(channels, np.abs(signals), bp.table)
    return Image(bp.table.grid, brute_force_image(bp.table, env, k), k, 10 ** (bp.options.threshold_db / 20))
