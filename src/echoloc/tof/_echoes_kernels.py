"""Compiled inner loops of the matched filter (:func:`echoloc.tof.echoes.matched_filter_batch`).

A frame of four channels holds a dozen echoes; written with numpy, each step of
detection, fitting and checking is an array call whose overhead outweighs its arithmetic,
and the batch path took many times as long as the correlation itself. Compiled, the same
arithmetic (per channel: candidates, sidelobe test, phase-refined fits, joint fits of
clusters, residual checks) pays no per-call overhead. The formulas are those of
:func:`echoloc.tof.echoes._isolated_echoes`, which stays as their readable statement
(the tests hold the two to the same answers); this module holds only their loops. The
same holds for CLEAN (:class:`echoloc.tof.echoes._Clean`): its whole run
(:func:`clean_run`: noise power, extraction, merging, joint fits, the model choice's
candidates, fits, checks and scores) is here, its Python statement there.

Where a test on noisy data decides (the median's partitions, the local-maximum test
above the threshold), the loops are written without branches: mispredicted branches
cost more than the arithmetic. Call the kernels from Python with every argument:
numba's dispatcher resolves a call that leaves defaults out on a slow path.

``cache=True`` keeps the machine code in ``__pycache__``: the first call in a fresh
environment compiles (some seconds), later processes load it.

The kernels Python calls once a frame run without the GIL (``nogil=True``; they touch no
Python object): `echoloc stream`'s receiving thread then reads and decodes the next frames
on the other core meanwhile, where it used to wait for the GIL and fall behind the wire
(`benchmarks/bench_stream.py --soak-minutes 0.5 --speed 34.32`; figures in the CHANGELOG).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import scipy.fft
from numpy.typing import NDArray

from echoloc._jit import njit, prange
from echoloc._linear_kernels import solve_in_place
from echoloc.tof.echoes import _PRECISION_AMPLITUDE, _PRECISION_POWER

if TYPE_CHECKING:
    from echoloc.tof.echoes import BatchConstants, EchoKernelArguments, FinishingConstants

# The parameters' types are those numba's dispatchers record for the pipeline's calls (every
# estimator on the simulated presets; the inlined helpers' from their callers). Arrays are
# C-contiguous and 1-D unless a trailing comment or the docstring gives their shape, but for
# ``table`` (MatchedFilter.acf_table: oversample rows of 2 half + 1 lags) and ``grid_b`` (>= count,
# 4; base0, row0, base1, row1 of each delay, with its weight in ``grid_w``: _prepare). Delays are
# float64 lags, amplitudes complex128 (real-valued where a fit takes real amplitudes), echo
# states int8, and a channel's correlation float32 (complex64 viewed as real, imaginary pairs).

_RefineScratch = tuple[
    NDArray[np.float64],  # new_tofs
    NDArray[np.complex128],  # new_amps
    NDArray[np.complex128],  # window
    NDArray[np.float64],  # joint_data (joint_w, 2)
    NDArray[np.bool_],  # joint_valid
    NDArray[np.float64],  # joint_t
    NDArray[np.complex128],  # joint_a
    NDArray[np.float64],  # joint_work
    NDArray[np.complex128],  # joint_new
]
""":func:`_refine_echoes`' scratch, as :func:`batch_echoes` allocates it (a numba tuple)."""

_Complex = NDArray[np.complex64] | NDArray[np.complex128]
""":func:`weigh_and_fold`'s arrays, in either precision (numba compiles it for each): complex64
from :func:`correlate_rows`; from MatchedFilter.correlate the weights complex128, the spectrum
complex128 (complex64 for float32 frames) and ``out`` their result type."""


@njit(cache=True, nogil=True)
def weigh_and_fold(
    spectrum: _Complex,  # (rows, bins)
    weights: _Complex,  # (>= bins,)
    out: _Complex,  # (rows, m): the result type of the two
) -> None:  # pragma: no cover - compiled
    """``out[r, k]`` = the sum of ``spectrum[r, j] * weights[j]`` over the bins j = k (mod m), m =
    ``out.shape[1]``: the matched filter's product spectrum folded for its shorter inverse FFT
    (:meth:`echoloc.tof.echoes.MatchedFilter._weigh_and_fold`), in one pass; bins past the
    spectrum's end are 0."""
    rows, bins = spectrum.shape
    m = out.shape[1]
    first = min(m, bins)
    for r in range(rows):
        for k in range(first):
            out[r, k] = spectrum[r, k] * weights[k]
        for k in range(first, m):
            out[r, k] = 0
        for start in range(m, bins, m):
            for k in range(start, min(start + m, bins)):
                out[r, k - start] += spectrum[r, k] * weights[k]


OK, TOO_MANY, CLOSE, TOO_BIG, LEFT_OVER, UNEXPLAINED = 0, 1, 2, 3, 4, 5
"""Status of a channel: fitted here, or why it goes to CLEAN."""


@njit(cache=True, nogil=True)
def correlate_rows(
    frames: NDArray[np.float64],  # (rows, samples)
    n_fft: int,
    n_ifft: int,
    weights: NDArray[np.complex64],  # (n_fft // 2 + 1,)
    workers: int,
) -> NDArray[np.complex64]:  # pragma: no cover
    """The matched filter's single-precision correlation of every row of ``frames`` (rows,
    samples; float64), as :meth:`echoloc.tof.echoes.MatchedFilter.correlate_single_rows` returns
    it: rows zero-padded (or cropped) to ``n_fft`` in float32, their rfft weighed by
    ``weights`` and folded to ``n_ifft`` bins (:func:`weigh_and_fold`), inverse FFT. The FFTs
    are scipy.fft's in compiled code (rocket-fft), on ``workers`` threads."""
    rows, n = frames.shape
    m = min(n, n_fft)
    padded = np.zeros((rows, n_fft), np.float32)
    padded[:, :m] = frames[:, :m]
    spectrum = scipy.fft.rfft(padded, axis=-1, workers=workers)
    folded = np.empty((rows, n_ifft), np.complex64)
    weigh_and_fold(spectrum, weights, folded)
    # (rows, n_ifft); scipy's stubs are missing (Any): the annotation states rocket-fft's type.
    correlation: NDArray[np.complex64] = scipy.fft.ifft(folded, axis=-1, overwrite_x=True, workers=workers)
    return correlation


@njit(cache=True, nogil=True)
def correlate_and_fit(arguments: EchoKernelArguments) -> None:  # pragma: no cover - compiled
    """:func:`correlate_rows` then :func:`batch_channels` on it, in one call: a stream's frame
    makes one call from Python for its echoes instead of four (two FFTs, the fold, the fits),
    which saves the overhead of three calls (`benchmarks/bench_fft_kernel.py` measures it).
    ``arguments`` (echoes.echo_kernel_arguments) are read by name; the echoes land in its
    ``out``, ``kept`` and ``ok``."""
    correlation = correlate_rows(
        arguments.frames, arguments.n_fft, arguments.n_ifft, arguments.weights, arguments.workers
    )
    batch_channels(
        arguments.parts,
        correlation.view(np.float32),
        arguments.n_lags,
        arguments.constants,
        arguments.finishing,
        arguments.out,
        arguments.kept,
        arguments.ok,
    )


@njit(cache=True, inline="always")
def _grid(u: int, tof: float) -> tuple[int, int, int, int, float]:  # pragma: no cover - compiled
    """Where ``tof`` falls in the sub-sample table: whole sample and row of the two nearest shifts, weight."""
    position = tof * u
    g = math.floor(position)
    gi = int(g)
    return gi // u, gi % u, (gi + 1) // u, (gi + 1) % u, position - g


@njit(cache=True, inline="always")
def _at(
    table: NDArray[np.complex128],
    half: int,
    base0: int,
    row0: int,
    base1: int,
    row1: int,
    weight: float,
    s: int,
) -> tuple[complex, complex]:  # pragma: no cover - compiled
    """R(s - tof) and (v1 - v0) for a delay on the grid (base0, row0, base1, row1, weight)."""
    width = 2 * half + 1
    lag0 = s - base0 + half
    lag1 = s - base1 + half
    v0r = v0i = v1r = v1i = 0.0
    if lag0 >= 0 and lag0 < width:
        v = table[row0, lag0]
        v0r, v0i = v.real, v.imag
    if lag1 >= 0 and lag1 < width:
        v = table[row1, lag1]
        v1r, v1i = v.real, v.imag
    dr, di = v1r - v0r, v1i - v0i
    return complex(v0r + weight * dr, v0i + weight * di), complex(dr, di)


@njit(cache=True)
def _prepare(
    u: int, tofs: NDArray[np.float64], grid_b: NDArray[np.int64], grid_w: NDArray[np.float64]
) -> None:  # pragma: no cover - compiled
    """Grid positions of every delay (grid_b: base0, row0, base1, row1; grid_w: weight)."""
    for e in range(len(tofs)):
        b0, r0, b1, r1, w = _grid(u, tofs[e])
        grid_b[e, 0], grid_b[e, 1], grid_b[e, 2], grid_b[e, 3] = b0, r0, b1, r1
        grid_w[e] = w


@njit(cache=True)
def _model(
    table: NDArray[np.complex128],
    half: int,
    grid_b: NDArray[np.int64],
    grid_w: NDArray[np.float64],
    amps: NDArray[np.complex128],
    count: int,
    s: int,
    skip_lo: int,
    skip_hi: int,
) -> complex:  # pragma: no cover - compiled
    """Sum of a_k R(s - tau_k) over echoes 0..count-1 except those in [skip_lo, skip_hi)."""
    width = 2 * half + 1
    total_r = 0.0
    total_i = 0.0
    for e in range(count):
        if skip_lo <= e < skip_hi:
            continue
        lag0 = s - grid_b[e, 0] + half
        lag1 = s - grid_b[e, 2] + half
        v0r = v0i = v1r = v1i = 0.0
        if lag0 >= 0 and lag0 < width:
            v = table[grid_b[e, 1], lag0]
            v0r, v0i = v.real, v.imag
        if lag1 >= 0 and lag1 < width:
            v = table[grid_b[e, 3], lag1]
            v1r, v1i = v.real, v.imag
        w = grid_w[e]
        xr = v0r + w * (v1r - v0r)
        xi = v0i + w * (v1i - v0i)
        a = amps[e]
        total_r += a.real * xr - a.imag * xi
        total_i += a.real * xi + a.imag * xr
    return complex(total_r, total_i)


@njit(cache=True)
def _median(values: NDArray[np.float64]) -> float:  # pragma: no cover - compiled
    """The median (mean of the two middle values for an even count), by quickselect."""
    scratch = np.empty((3, len(values)), dtype=values.dtype)
    return _median_in(values, scratch[0], scratch[1], scratch[2])


@njit(cache=True)
def _median_in(
    values: NDArray[np.float64],
    a: NDArray[np.float64],
    below: NDArray[np.float64],
    above: NDArray[np.float64],
) -> float:  # pragma: no cover - compiled
    """:func:`_median` with scratch ``a``, ``below``, ``above`` (at least ``len(values)`` each),
    by :func:`_select`."""
    n = len(values)
    k = n // 2
    a[:n] = values
    upper = _select(a[:n], k, below, above)
    if n % 2:
        return upper
    return _mean_of_middles(values, upper, 0, k)


_EXPONENT_BUCKETS = 2048
_MANTISSA_BUCKETS = 256
_RADIX_BAND = 32
""":func:`_noise_median`'s counters, one per float64 exponent, then one per value of the next 8
bits of a chosen exponent; and the most values it sorts among those sharing their top 20 bits."""


@njit(cache=True)
def _noise_median(
    values: NDArray[np.float64], counts: NDArray[np.int32], scratch: NDArray[np.float64]
) -> float:  # pragma: no cover - compiled
    """:func:`_median_in` of ``values`` (C-contiguous) by radix selection on their IEEE-754 bits:
    the same value, in less time on a channel's 600 noise powers (`benchmarks/bench_noise_median.py`
    measures it).

    The bits of non-negative floats sort as the floats do. Counting the values per exponent
    finds the exponent of the middle rank, counting that exponent's values per next 8 bits its
    band of 2^-8 relative width, and a pass collects the band (a few values on noise) and the
    largest value below it; the middle values are picked there. ``counts`` (int32,
    :data:`_EXPONENT_BUCKETS` + :data:`_MANTISSA_BUCKETS`) is zero on entry and left so;
    ``scratch`` is :func:`_median_in`'s (3, >= len(values)). Values with a negative, infinite
    or NaN member, or more than :data:`_RADIX_BAND` in the band (a dead channel's equal
    values), go to :func:`_median_in`.
    """
    n = values.shape[0]
    if n == 0:
        return _median_in(values, scratch[0], scratch[1], scratch[2])
    k = n // 2
    bits = values.view(np.int64)
    exponents = counts[:_EXPONENT_BUCKETS]
    mantissas = counts[_EXPONENT_BUCKETS:]
    lo, hi = _EXPONENT_BUCKETS - 1, -_EXPONENT_BUCKETS
    for i in range(n):
        e = bits[i] >> 52  # negative for a negative value (its index wraps; cleared below)
        exponents[e] += 1
        lo = min(lo, e)
        hi = max(hi, e)
    if lo < 0 or hi == _EXPONENT_BUCKETS - 1:
        exponents[:] = 0
        return _median_in(values, scratch[0], scratch[1], scratch[2])
    below = 0
    chosen = lo
    for e in range(lo, hi + 1):
        if below + exponents[e] > k:
            chosen = e
            break
        below += exponents[e]
    exponents[lo : hi + 1] = 0
    for i in range(n):
        b = bits[i]
        mantissas[(b >> 44) & (_MANTISSA_BUCKETS - 1)] += (b >> 52) == chosen
    top = 0
    for m in range(_MANTISSA_BUCKETS):
        if below + mantissas[m] > k:
            top = m
            break
        below += mantissas[m]
    mantissas[:] = 0
    key = (chosen << 8) | top
    band = scratch[0]
    count = 0
    under = -np.inf
    for i in range(n):  # branch-free: every value is written, the count advances by the test
        v = values[i]
        b = bits[i] >> 44
        band[count] = v
        count += b == key
        under = max(under, v if b < key else -np.inf)
    if count > _RADIX_BAND:
        return _median_in(values, scratch[0], scratch[1], scratch[2])
    rank = k - below
    for i in range(rank + 1):  # the band's smallest values in order, up to the middle rank
        best = i
        for j in range(i + 1, count):
            if band[j] < band[best]:
                best = j
        band[i], band[best] = band[best], band[i]
    upper = float(band[rank])
    if n % 2:
        return upper
    lower = float(band[rank - 1]) if rank > 0 else float(under)
    return 0.5 * (lower + upper)


@njit(cache=True, inline="always")
def _mean_of_middles(
    values: NDArray[np.float64], upper: float, smaller: int, k: int
) -> float:  # pragma: no cover
    """The median of an even count from its upper middle value ``upper`` (rank ``k``): the mean
    with the largest of ``values`` below it, or with ``upper`` itself when it repeats there.
    ``smaller`` counts the values below ``upper`` that ``values`` leaves out (all below it)."""
    lower = -np.inf
    for i in range(len(values)):
        v = values[i]
        smaller += v < upper
        lower = max(lower, v if v < upper else -np.inf)
    if smaller < k:
        lower = upper
    return 0.5 * (float(lower) + float(upper))


@njit(cache=True)
def _evaluate(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    data: NDArray[np.float64],  # (w, 2)
    lo: int,
    valid: NDArray[np.bool_],
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    shapes: NDArray[np.float64],  # (k, w, 2)
    slopes: NDArray[np.float64],  # (k, w, 2)
    residual: NDArray[np.float64],  # (w, 2)
) -> float:  # pragma: no cover - compiled
    """Shapes and slopes (k, w, 2: real, imaginary) over samples lo..lo+w-1, the residual
    data - model (w, 2; 0 where not valid) and its cost |residual|^2."""
    k, w = shapes.shape[0], shapes.shape[1]
    width = 2 * half + 1
    for m in range(k):
        b0, r0, b1, r1, wt = _grid(u, tofs[m])
        for j in range(w):
            v0r = v0i = v1r = v1i = 0.0
            if valid[j]:
                lag0 = lo + j - b0 + half
                lag1 = lo + j - b1 + half
                if lag0 >= 0 and lag0 < width:
                    v = table[r0, lag0]
                    v0r, v0i = v.real, v.imag
                if lag1 >= 0 and lag1 < width:
                    v = table[r1, lag1]
                    v1r, v1i = v.real, v.imag
            dr, di = v1r - v0r, v1i - v0i
            shapes[m, j, 0] = v0r + wt * dr
            shapes[m, j, 1] = v0i + wt * di
            slopes[m, j, 0] = dr * u
            slopes[m, j, 1] = di * u
    cost = 0.0
    for j in range(w):
        rr, ri = 0.0, 0.0
        if valid[j]:
            rr, ri = data[j, 0], data[j, 1]
            for m in range(k):
                ar, ai = amps[m].real, amps[m].imag
                sr, si = shapes[m, j, 0], shapes[m, j, 1]
                rr -= ar * sr - ai * si
                ri -= ar * si + ai * sr
        residual[j, 0] = rr
        residual[j, 1] = ri
        cost += rr * rr + ri * ri
    return cost


@njit(cache=True)
def joint_fit(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    data: NDArray[np.float64],  # (w, 2): real and imaginary parts
    lo: int,
    valid: NDArray[np.bool_],
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    real: bool,
    iterations: int,
    converge: bool = False,
    rotation: float = 0.0,
    tolerance: float = 1e-6,
    gain: float = 0.0,
) -> float:  # pragma: no cover - compiled
    """Levenberg-Marquardt of sum_k a_k R(s - tau_k) to data (w, 2), in place; the final cost.

    As echoes._joint_fit_batch does for one row: ``iterations`` steps, or with
    ``converge`` at most that many, stopping once a step moves no delay by more than
    ``tolerance`` samples, or lowers the cost by less than the fraction ``gain`` of it,
    or the damping has grown past 1e8 (no step lowers the cost).

    With complex amplitudes and a ``rotation`` (the carrier's rate, rad/sample), the
    amplitudes are stepped in the frame that turns with the carrier, ``b_k = a_k
    exp(-i rotation tau_k)``: ``b_k R(s - tau_k) exp(i rotation tau_k)`` is the envelope
    moving with the delay, where ``a_k R(s - tau_k)`` turns its phase with it, so that a
    step in a delay linearised at fixed ``a_k`` is good only for a small fraction of a
    carrier cycle and the fit crawls. The same cost, the same minima; fewer steps.

    Its scratch is allocated here; :func:`_joint_fit_into` takes it from the caller.
    """
    k = len(tofs)
    w = data.shape[0]
    work = np.empty(_fit_scratch_size(k, w))
    new_amps = np.empty(k, dtype=np.complex128)
    return _joint_fit_into(
        table,
        u,
        half,
        data,
        lo,
        valid,
        tofs,
        amps,
        real,
        iterations,
        converge,
        rotation,
        tolerance,
        gain,
        work,
        new_amps,
    )


@njit(cache=True, inline="always")
def _fit_scratch_size(k: int, w: int) -> int:  # pragma: no cover - compiled
    """Floats of scratch :func:`_joint_fit_into` needs for ``k`` echoes over ``w`` samples."""
    p = 3 * k
    return 4 * k * w * 2 + 2 * w * 2 + p * w * 2 + 2 * p * p + 3 * p + 3 * k


@njit(cache=True)
def _joint_fit_into(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    data: NDArray[np.float64],  # (w, 2): real and imaginary parts
    lo: int,
    valid: NDArray[np.bool_],
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    real: bool,
    iterations: int,
    converge: bool,
    rotation: float,
    tolerance: float,
    gain: float,
    work: NDArray[np.float64],
    new_amps: NDArray[np.complex128],
) -> float:  # pragma: no cover - compiled
    """:func:`joint_fit` with its scratch passed in (``work``: :func:`_fit_scratch_size` floats or
    more; ``new_amps``: ``len(tofs)`` complex or more): allocating them at every call would
    add up, as CLEAN fits a few dozen candidate models a channel."""
    k = len(tofs)
    w = data.shape[0]
    p = k * (2 if real else 3)
    # Views of the scratch, carved in order (a view is not an allocation).
    size = k * w * 2
    shapes = work[0:size].reshape((k, w, 2))
    slopes = work[size : 2 * size].reshape((k, w, 2))
    trial_shapes = work[2 * size : 3 * size].reshape((k, w, 2))
    trial_slopes = work[3 * size : 4 * size].reshape((k, w, 2))
    at = 4 * size
    residual = work[at : at + 2 * w].reshape((w, 2))
    trial_residual = work[at + 2 * w : at + 4 * w].reshape((w, 2))
    at += 4 * w
    jac = work[at : at + p * w * 2].reshape((p, w, 2))
    at += p * w * 2
    undamped = work[at : at + p * p].reshape((p, p))
    normal = work[at + p * p : at + 2 * p * p].reshape((p, p))
    at += 2 * p * p
    gradient = work[at : at + p]
    rhs = work[at + p : at + 2 * p]
    step = work[at + 2 * p : at + 3 * p]
    new_tofs = work[at + 3 * p : at + 3 * p + k]
    # cos and sin of the carrier phase at each delay of the current point: computed once a point,
    # for its normal equations and every trial step from it (the trial's own turn is its move's).
    turn_c = work[at + 3 * p + k : at + 3 * p + 2 * k]
    turn_s = work[at + 3 * p + 2 * k : at + 3 * p + 3 * k]
    trial_amps = new_amps[:k]
    cost = _evaluate(table, u, half, data, lo, valid, tofs, amps, shapes, slopes, residual)
    damping = 1e-3
    stale = True  # the normal equations at the current point are to be computed
    for _ in range(iterations):
        if stale:
            if rotation != 0.0 and not real:
                for m in range(k):
                    turn_c[m], turn_s[m] = math.cos(rotation * tofs[m]), math.sin(rotation * tofs[m])
                _rotate_normal_equations(
                    shapes, slopes, residual, turn_c, turn_s, amps, rotation, jac, undamped, gradient
                )
            else:
                _normal_equations(shapes, slopes, residual, amps, real, jac, undamped, gradient)
            stale = False
        # A rejected step leaves the point, so its normal equations, as they were: only the
        # damping changes.
        normal[:] = undamped
        rhs[:] = gradient
        for a in range(p):
            d = normal[a, a]
            normal[a, a] = d + damping * d + (1.0 if d == 0 else 0.0)
        if not solve_in_place(normal, rhs, step):
            step[:] = np.nan  # a singular system: a NaN step
        for m in range(k):
            new_tofs[m] = tofs[m] + min(max(step[m], -2.0), 2.0)
            if rotation != 0.0 and not real:
                # b + db at the new delay: a_new = (a + db exp(i r tau)) exp(i r (tau_new - tau)).
                turn = complex(turn_c[m], turn_s[m])
                moved = new_tofs[m] - tofs[m]
                trial_amps[m] = (amps[m] + complex(step[k + m], step[2 * k + m]) * turn) * complex(
                    math.cos(rotation * moved), math.sin(rotation * moved)
                )
                continue
            trial_amps[m] = amps[m] + step[k + m]
            if not real:
                trial_amps[m] += 1j * step[2 * k + m]
        trial = _evaluate(
            table, u, half, data, lo, valid, new_tofs, trial_amps, trial_shapes, trial_slopes, trial_residual
        )
        if trial < cost:
            moved = 0.0
            for m in range(k):
                moved = max(moved, abs(new_tofs[m] - tofs[m]))
            tofs[:] = new_tofs
            amps[:] = trial_amps
            # The trial's shapes, slopes and residual become the point's (buffers swapped, not copied).
            shapes, trial_shapes = trial_shapes, shapes
            slopes, trial_slopes = trial_slopes, slopes
            residual, trial_residual = trial_residual, residual
            lowered = cost - trial
            cost = trial
            stale = True
            damping /= 4
            if converge and (moved < tolerance or lowered < gain * cost):
                break
        else:
            damping *= 8
            if converge and damping > 1e8:
                break
    return cost


@njit(cache=True, inline="always")
def _lone_pass(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    data: NDArray[np.float64],
    lo: int,
    valid: NDArray[np.bool_],
    tof: float,
    ar: float,
    ai: float,
    normal: bool,
) -> tuple[float, float, float, float, float, float]:  # pragma: no cover - compiled
    """One pass of :func:`_lone_fit` over the window: the cost |data - a R(s - tof)|^2 and, with
    ``normal``, the normal matrix (n00, n01, n11) and gradient (g0, g1) of (delay, real
    amplitude), as :func:`_evaluate` and :func:`_normal_equations` make them for one echo."""
    width = 2 * half + 1
    b0, r0, b1, r1, wt = _grid(u, tof)
    cost = n00 = n01 = n11 = g0 = g1 = 0.0
    for j in range(data.shape[0]):
        if not valid[j]:
            continue
        lag0 = lo + j - b0 + half
        lag1 = lo + j - b1 + half
        v0r = v0i = v1r = v1i = 0.0
        if lag0 >= 0 and lag0 < width:
            v = table[r0, lag0]
            v0r, v0i = v.real, v.imag
        if lag1 >= 0 and lag1 < width:
            v = table[r1, lag1]
            v1r, v1i = v.real, v.imag
        dr, di = v1r - v0r, v1i - v0i
        sr, si = v0r + wt * dr, v0i + wt * di
        rr = data[j, 0] - (ar * sr - ai * si)
        ri = data[j, 1] - (ar * si + ai * sr)
        cost += rr * rr + ri * ri
        if normal:
            pr, pi = dr * u, di * u
            jr, ji = ar * pr - ai * pi, ar * pi + ai * pr
            n00 += jr * jr + ji * ji
            n01 += jr * sr + ji * si
            n11 += sr * sr + si * si
            g0 += jr * rr + ji * ri
            g1 += sr * rr + si * ri
    return cost, n00, n01, n11, g0, g1


@njit(cache=True)
def _lone_fit(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    data: NDArray[np.float64],  # (w, 2)
    lo: int,
    valid: NDArray[np.bool_],
    tof: float,
    amp: complex,
    iterations: int,
) -> tuple[float, complex]:  # pragma: no cover - compiled
    """:func:`_joint_fit_into` of one echo with a real amplitude, ``iterations`` Levenberg-Marquardt
    steps (no convergence test), in scalars: the same steps, with the window's sums in another
    order (rounding of ~1e-16). The batch path steps every lone echo so; the general fit's
    scratch arrays and loops over echoes took a sizeable share of the batch path's time for it.
    Returns the delay (samples) and the amplitude."""
    ar, ai = amp.real, amp.imag
    cost, n00, n01, n11, g0, g1 = _lone_pass(table, u, half, data, lo, valid, tof, ar, ai, True)
    damping = 1e-3
    for step_index in range(iterations):
        m00 = n00 + damping * n00 + (1.0 if n00 == 0 else 0.0)
        m11 = n11 + damping * n11 + (1.0 if n11 == 0 else 0.0)
        # m x = g by Gaussian elimination with partial pivoting, as solve_in_place.
        a00, a01, a10, a11, v0, v1 = m00, n01, n01, m11, g0, g1
        if abs(a10) > abs(a00):
            a00, a01, a10, a11, v0, v1 = a10, a11, a00, a01, v1, v0
        if a00 == 0.0 or not np.isfinite(a00):
            break
        f = a10 / a00
        a11 -= f * a01
        v1 -= f * v0
        if a11 == 0.0 or not np.isfinite(a11):
            break
        step_amp = v1 / a11
        step_tof = (v0 - a01 * step_amp) / a00
        if not (np.isfinite(step_tof) and np.isfinite(step_amp)):
            break
        new_tof = tof + min(max(step_tof, -2.0), 2.0)
        new_ar = ar + step_amp
        more = step_index + 1 < iterations
        trial, t00, t01, t11, h0, h1 = _lone_pass(table, u, half, data, lo, valid, new_tof, new_ar, ai, more)
        if trial < cost:
            tof, ar, cost = new_tof, new_ar, trial
            n00, n01, n11, g0, g1 = t00, t01, t11, h0, h1
            damping /= 4
        else:
            damping *= 8
    return tof, complex(ar, ai)


@njit(cache=True, fastmath={"reassoc"})
def _products(
    jac: NDArray[np.float64],  # (p, n)
    residual: NDArray[np.float64],
    normal: NDArray[np.float64],  # (p, p)
    gradient: NDArray[np.float64],
) -> None:  # pragma: no cover - compiled
    """``normal = jac jac^T`` and ``gradient = jac residual`` (jac (p, n), residual (n,): real and
    imaginary parts side by side), the inner products of a fit step.

    The sums may be reassociated (``fastmath={"reassoc"}``), so that they run in SIMD lanes:
    faster complex-amplitude steps, at rounding differences of 1e-16.
    """
    p, n = jac.shape
    for a in range(p):
        for b in range(a, p):
            acc = 0.0
            for i in range(n):
                acc += jac[a, i] * jac[b, i]
            normal[a, b] = acc
            normal[b, a] = acc
        acc = 0.0
        for i in range(n):
            acc += jac[a, i] * residual[i]
        gradient[a] = acc


@njit(cache=True)
def _normal_equations(
    shapes: NDArray[np.float64],  # (k, w, 2)
    slopes: NDArray[np.float64],  # (k, w, 2)
    residual: NDArray[np.float64],  # (w, 2)
    amps: NDArray[np.complex128],
    real: bool,
    jac: NDArray[np.float64],  # (p, w, 2)
    normal: NDArray[np.float64],  # (p, p)
    gradient: NDArray[np.float64],
) -> None:  # pragma: no cover - compiled
    """Jacobian (d model / d parameter: delays, real parts, imaginary parts unless ``real``),
    the undamped normal matrix ``J^T J`` and the gradient ``J^T residual`` of :func:`joint_fit`."""
    k, w = shapes.shape[0], shapes.shape[1]
    p = normal.shape[0]
    for m in range(k):
        ar, ai = amps[m].real, amps[m].imag
        for j in range(w):
            sr, si = slopes[m, j, 0], slopes[m, j, 1]
            jac[m, j, 0] = ar * sr - ai * si
            jac[m, j, 1] = ar * si + ai * sr
            jac[k + m, j, 0] = shapes[m, j, 0]
            jac[k + m, j, 1] = shapes[m, j, 1]
            if not real:
                jac[2 * k + m, j, 0] = -shapes[m, j, 1]
                jac[2 * k + m, j, 1] = shapes[m, j, 0]
    _products(jac.reshape((p, 2 * w)), residual.reshape(2 * w), normal, gradient)


@njit(cache=True)
def _rotate_normal_equations(
    shapes: NDArray[np.float64],  # (k, w, 2)
    slopes: NDArray[np.float64],  # (k, w, 2)
    residual: NDArray[np.float64],  # (w, 2)
    turn_c: NDArray[np.float64],
    turn_s: NDArray[np.float64],
    amps: NDArray[np.complex128],
    rotation: float,
    jac: NDArray[np.float64],  # (p, w, 2)
    normal: NDArray[np.float64],  # (p, p)
    gradient: NDArray[np.float64],
) -> None:  # pragma: no cover - compiled
    """:func:`_normal_equations` for complex amplitudes stepped in the frame turning with the carrier.

    d model / d tau_k = a_k (R' + i rotation R) (R' the slope in the delay), d model /
    d Re b_k = exp(i rotation tau_k) R, d model / d Im b_k = i exp(i rotation tau_k) R;
    ``turn_c``/``turn_s`` hold cos and sin of ``rotation tau_k``.
    """
    k, w = shapes.shape[0], shapes.shape[1]
    p = normal.shape[0]
    for m in range(k):
        ar, ai = amps[m].real, amps[m].imag
        c, sn = turn_c[m], turn_s[m]
        for j in range(w):
            xr, xi = shapes[m, j, 0], shapes[m, j, 1]
            dr = slopes[m, j, 0] - rotation * xi
            di = slopes[m, j, 1] + rotation * xr
            jac[m, j, 0] = ar * dr - ai * di
            jac[m, j, 1] = ar * di + ai * dr
            er, ei = c * xr - sn * xi, c * xi + sn * xr
            jac[k + m, j, 0] = er
            jac[k + m, j, 1] = ei
            jac[2 * k + m, j, 0] = -ei
            jac[2 * k + m, j, 1] = er
    _products(jac.reshape((p, 2 * w)), residual.reshape(2 * w), normal, gradient)


@njit(cache=True)
def _fit_peak(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    rate: float,
    corr: NDArray[np.float32],  # (>= 2 n,): real and imaginary parts side by side
    n: int,
    peak: int,
    fit_half: int,
    grid_b: NDArray[np.int64],
    grid_w: NDArray[np.float64],
    amps: NDArray[np.complex128],
    count: int,
    skip: int,
    window: NDArray[np.complex128],
) -> tuple[float, complex]:  # pragma: no cover - compiled
    """One echo as echoes._fit_peaks fits it, the other echoes' model (all but ``skip``) taken out.

    ``corr`` holds the channel's first ``n`` correlation samples (real, imaginary side by
    side); ``window`` is scratch for the 2 fit_half + 1 samples around the peak, each
    computed once (the peak's neighbours are among them).
    """
    for i in range(2 * fit_half + 1):
        s = peak - fit_half + i
        if 0 <= s < n:
            window[i] = complex(corr[2 * s], corr[2 * s + 1]) - _model(
                table, half, grid_b, grid_w, amps, count, s, skip, skip + 1
            )
    # The peak and its neighbours, as scalars (three-element arrays here cost two allocations a fit).
    s0, s1, s2 = min(max(peak - 1, 0), n - 1), min(max(peak, 0), n - 1), min(max(peak + 1, 0), n - 1)
    v0, v1, v2 = window[s0 - peak + fit_half], window[s1 - peak + fit_half], window[s2 - peak + fit_half]
    a, b, c = abs(v0), abs(v1), abs(v2)
    curvature = a - 2 * b + c
    offset = 0.0
    if curvature < 0:
        offset = min(max(0.5 * (a - c) / curvature, -0.5), 0.5)
    coarse = peak + offset
    period = math.pi / rate
    weighted = 0.0
    total = 0.0
    for s, value, magnitude in ((s0, v0, a), (s1, v1, b), (s2, v2, c)):
        estimate = s - math.atan2(value.imag, value.real) / rate
        estimate += period * np.round((coarse - estimate) / period)
        weighted += magnitude**2 * estimate
        total += magnitude**2
    tof = weighted / max(total, 1e-300)
    if abs(tof - coarse) > 1.5:
        tof = coarse
    b0, r0, b1, r1, wt = _grid(u, tof)
    num = 0j
    den = 0.0
    for i in range(2 * fit_half + 1):
        s = peak - fit_half + i
        if s < 0 or s >= n:
            continue
        shape, _ = _at(table, half, b0, r0, b1, r1, wt, s)
        num += shape.conjugate() * window[i]
        den += shape.real * shape.real + shape.imag * shape.imag
    return tof, num / max(den, 1e-300)


@njit(cache=True, inline="always")
def _sort_descending(
    keys: NDArray[np.float64], values: NDArray[np.int64], count: int
) -> None:  # pragma: no cover - compiled
    """Sort keys[:count] (and values alongside) largest first, equal keys in their order (stable).

    Insertion sort: a channel has a handful of candidates, and np.argsort would allocate.
    """
    for i in range(1, count):
        key, value = keys[i], values[i]
        j = i
        while j > 0 and keys[j - 1] < key:
            keys[j], values[j] = keys[j - 1], values[j - 1]
            j -= 1
        keys[j], values[j] = key, value


@njit(cache=True)
def _channel_checks(
    table: NDArray[np.complex128],
    half: int,
    row: NDArray[np.float32],  # (>= 2 n,): real and imaginary parts side by side
    n: int,
    grid_b: NDArray[np.int64],
    grid_w: NDArray[np.float64],
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    peaks: NDArray[np.int64],
    count: int,
    cand_k: NDArray[np.int64],
    accepted: NDArray[np.bool_],
    n_cand: int,
    fit_half: int,
    span: int,
    threshold: float,
    power: float,
    acf_energy: float,
    residual_power: NDArray[np.float64],
    state: NDArray[np.int8],  # FREE, BORN or WAIVED
) -> tuple[int, int]:  # pragma: no cover - compiled
    """The batch path's checks of a channel's fitted echoes (``grid_b``/``grid_w`` prepared for
    ``tofs[:count]``): its status, and the echo that failed (-1: none, or a rejected candidate).

    The model must explain the main lobe around each echo's peak, every rejected candidate,
    and (CLEAN's split test) two main lobes around each echo. Of the echoes that fail, the one
    whose two main lobes hold the most unexplained energy (against what the test allows) is
    returned: a pair fitted as one echo leaves its sidelobes' misfit on its neighbours too.
    The residual around an echo is computed once for the two windows around it (its peak's
    main lobe lies within the two main lobes). WAIVED echoes (``state``) are not checked, nor
    rejected candidates within their template's reach (where CLEAN, merging the pair into one
    echo, leaves the pair's misfit too).
    """
    worst_status, worst, worst_excess = OK, -1, -1.0
    for e in range(count):
        if state[e] == WAIVED:
            continue
        status = OK
        centre = int(np.round(tofs[e]))
        lo = min(centre - span, peaks[e] - fit_half)
        hi = max(centre + span, peaks[e] + fit_half)
        for s in range(max(lo, 0), min(hi, n - 1) + 1):
            window_r = complex(row[2 * s], row[2 * s + 1]) - _model(
                table, half, grid_b, grid_w, amps, count, s, 0, 0
            )
            residual_power[s] = window_r.real * window_r.real + window_r.imag * window_r.imag
        for i in range(2 * fit_half + 1):
            s = min(max(peaks[e] - fit_half + i, 0), n - 1)
            if residual_power[s] > threshold:
                status = LEFT_OVER
        cost = 0.0
        inside = 0
        for i in range(2 * span + 1):
            s = centre - span + i
            if 0 <= s < n:
                cost += residual_power[s]
                inside += 1
        magnitude = abs(amps[e])
        allowed = max(3.0 * power * inside, 0.003 * magnitude * magnitude * acf_energy)
        if cost >= allowed:
            status = UNEXPLAINED
        if status != OK and cost / allowed > worst_excess:
            worst_status, worst, worst_excess = status, e, cost / allowed
    if worst >= 0:
        return worst_status, worst
    for j in range(n_cand):
        if not accepted[j]:
            s = cand_k[j]
            near_waived = False
            for e in range(count):
                near_waived |= state[e] == WAIVED and abs(s - tofs[e]) <= half
            if near_waived:
                continue
            r = complex(row[2 * s], row[2 * s + 1]) - _model(
                table, half, grid_b, grid_w, amps, count, s, 0, 0
            )
            if r.real * r.real + r.imag * r.imag > threshold:
                return LEFT_OVER, -1
    return OK, -1


FREE, BORN, WAIVED = 0, 1, 2
"""State of an echo in the batch path: as found, one of a split's pair, or one echo standing for
a pair too close to resolve (the checks pass it over)."""
NO_PAIR, MERGED = -1, -2
"""What :func:`_split_echo` returns instead of a count: no plausible pair, or a pair too close to resolve."""

# A split searches a grid of delays one lag apart: its gain varies over the envelope's scale (the
# complex amplitudes take up the carrier phase), a main lobe of 8.5 lags. Half a lag was slower
# on the five-reflector bench frames and kept 130 of their 141 unexplained channels from CLEAN
# against 126. On whole lags every shape is the one before it moved by a sample, which
# _split_echo's Gram matrix is built on.
_SPLIT_ITERATIONS = 200
"""Most Levenberg-Marquardt steps of a split's fits, each stopping once converged (as CLEAN's)."""
_SPLIT_TOLERANCE = 1e-3
_SPLIT_GAIN = 1e-3
"""A split's real-amplitude fits stop once a step moves no delay by more than this (samples), or
lowers the cost by less than this fraction of it: they only choose the basin (half a carrier
cycle wide), and the cluster's joint fit after the split settles the pair in it."""


@njit(cache=True)
def _window_max(
    keys: NDArray[np.int64],
    values: NDArray[np.float64],
    count: int,
    reach: int,
    out: NDArray[np.float64],
    queue: NDArray[np.int64],
) -> None:  # pragma: no cover - compiled
    """``out[i]`` = the largest ``values[j]``, j < ``count``, with ``|keys[j] - keys[i]| <= reach``
    (``keys`` ascending; ``i`` itself included): a sliding maximum over a monotone queue of
    indices (``queue``, room for ``count``), one pass."""
    head = 0
    tail = 0
    right = 0
    for i in range(count):
        while right < count and keys[right] <= keys[i] + reach:
            while tail > head and values[queue[tail - 1]] <= values[right]:
                tail -= 1
            queue[tail] = right
            tail += 1
            right += 1
        while keys[queue[head]] < keys[i] - reach:
            head += 1
        out[i] = values[queue[head]]


@njit(cache=True)
def _local_floor(
    keys: NDArray[np.int64],
    power: NDArray[np.float64],
    count: int,
    reach: int,
    out: NDArray[np.float64],
    scratch: NDArray[np.float64],
    queue: NDArray[np.int64],
) -> None:  # pragma: no cover - compiled
    """The dynamic range's reference for each candidate (echoes._local_strongest): ``out[i]`` = the
    largest power among the candidates within ``reach`` lags of candidate i that are the largest
    within ``reach`` lags of themselves (certain echoes: no stronger one's sidelobes reach them), 0
    if none. ``keys`` (the candidates' lags) ascending; ``scratch`` and ``queue`` room for ``count``."""
    _window_max(keys, power, count, reach, scratch, queue)
    for i in range(count):
        scratch[i] = power[i] if power[i] >= scratch[i] else 0.0
    _window_max(keys, scratch, count, reach, out, queue)


@njit(cache=True, inline="always")
def _sort_by_delay(
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    peaks: NDArray[np.int64],
    state: NDArray[np.int8],
    count: int,
) -> None:  # pragma: no cover
    """Sort the first ``count`` echoes by delay, their amplitudes, peaks and states alongside
    (stable insertion sort: a channel has a handful, and np.argsort would allocate)."""
    for i in range(1, count):
        t, a, pk, st = tofs[i], amps[i], peaks[i], state[i]
        j = i
        while j > 0 and tofs[j - 1] > t:
            tofs[j], amps[j], peaks[j], state[j] = tofs[j - 1], amps[j - 1], peaks[j - 1], state[j - 1]
            j -= 1
        tofs[j], amps[j], peaks[j], state[j] = t, a, pk, st


@njit(cache=True, inline="always")
def _settle_real(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    data: NDArray[np.float64],
    lo: int,
    valid: NDArray[np.bool_],
    t: NDArray[np.float64],
    a: NDArray[np.complex128],
    work: NDArray[np.float64],
    new_amps: NDArray[np.complex128],
) -> float:  # pragma: no cover - compiled
    """A split's real-amplitude fit of the pair ``t``/``a`` to ``data``, in place, to the basin's
    floor (:data:`_SPLIT_TOLERANCE`, :data:`_SPLIT_GAIN`); its cost."""
    return _joint_fit_into(
        table,
        u,
        half,
        data,
        lo,
        valid,
        t,
        a,
        True,
        _SPLIT_ITERATIONS,
        True,
        0.0,
        _SPLIT_TOLERANCE,
        _SPLIT_GAIN,
        work,
        new_amps,
    )


@njit(cache=True)
def _pair_plausible(
    t: NDArray[np.float64],
    a: NDArray[np.complex128],
    lo: int,
    hi: int,
    merge_samples: float,
    mainlobe: float,
    threshold: float,
) -> bool:  # pragma: no cover - compiled
    """Whether two fitted echoes make a pair CLEAN's model choice would keep: inside the window,
    both above the threshold (on |a|^2), a quarter main lobe apart, and _clean_plausible."""
    for i in range(2):
        if not (np.isfinite(t[i]) and lo <= t[i] < hi and abs(a[i]) ** 2 >= threshold):
            return False
    if abs(t[1] - t[0]) < merge_samples:
        return False
    return _clean_plausible(t, a, mainlobe)


@njit(cache=True)
def _split_echo(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    rate: float,
    row: NDArray[np.float32],  # (>= 2 n,): real and imaginary parts side by side
    n: int,
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    peaks: NDArray[np.int64],
    state: NDArray[np.int8],  # FREE, BORN or WAIVED
    count: int,
    e: int,
    reach: float,
    grid_b: NDArray[np.int64],
    grid_w: NDArray[np.float64],
    fit_half: int,
    mainlobe: float,
    threshold: float,
    data: NDArray[np.float64],  # (split_w, 2)
    valid: NDArray[np.bool_],
    shapes: NDArray[np.complex128],  # (split_grid, split_w)
    overlap: NDArray[np.complex128],
    energy: NDArray[np.float64],
    work: NDArray[np.float64],
    new_amps: NDArray[np.complex128],
    pair_t: NDArray[np.float64],
    pair_a: NDArray[np.complex128],
) -> int:  # pragma: no cover - compiled
    """Echo ``e`` of ``tofs``/``amps[:count]`` (real amplitudes; ``grid_b``/``grid_w`` prepared)
    refitted as two echoes within a main lobe of it, in place, together with the echoes within
    ``reach`` of it (the members: the rest of a pair whose joint fit settled wrong, or peaks
    of the pair's interference). Returns the new count: the members replaced by the pair,
    sorted by delay, the pair BORN in ``state`` with the first and last members' peaks. Else
    nothing changes: MERGED when ``e`` stands alone and the best pair, started closer than a
    quarter main lobe, settles no farther apart (CLEAN would merge it into one echo), NO_PAIR
    when no plausible pair fits.

    The data are the correlation less the other echoes' model, from a main lobe before the
    first member to a main lobe after the last and half a main lobe beyond. The pair starts
    from the global least-squares fit with complex amplitudes over a grid of delays
    a lag apart (variable projection: for shapes S_g, S_h the fit removes
    ``b^H G^-1 b`` of the data's energy, b their inner products with the data, G their Gram
    matrix), so no local minimum traps it. Levenberg-Marquardt with complex, then real
    amplitudes settles it. When that leaves more than ``threshold`` in the window, then as
    CLEAN's model choice does, each member, and then both together, is tried half a carrier
    cycle either way (amplitude negated: with real amplitudes the fit has a minimum every
    half cycle), and the lowest cost among plausible pairs (:func:`_pair_plausible`) wins.
    """
    first_member = last_member = e
    while first_member > 0 and tofs[e] - tofs[first_member - 1] <= reach:
        first_member -= 1
    while last_member < count - 1 and tofs[last_member + 1] - tofs[e] <= reach:
        last_member += 1
    members = last_member - first_member + 1
    start, stop = tofs[first_member] - mainlobe, tofs[last_member] + mainlobe
    lo = max(math.floor(start) - fit_half, 0)
    hi = min(math.ceil(stop) + fit_half + 1, n, lo + data.shape[0])
    w = hi - lo
    if w < 4:
        return NO_PAIR
    d = data[:w]
    ok = valid[:w]
    for j in range(w):
        s = lo + j
        other = _model(table, half, grid_b, grid_w, amps, count, s, first_member, last_member + 1)
        d[j, 0] = row[2 * s] - other.real
        d[j, 1] = row[2 * s + 1] - other.imag
        ok[j] = True
    first = float(math.floor(start))
    n_grid = min(int(stop - start) + 3, shapes.shape[0])
    b0, r0, b1, r1, wt = _grid(u, first)
    for g in range(n_grid):
        # The shape of delay first + g is that of first + g - 1 a sample later: one new sample.
        if g == 0:
            for j in range(w):
                shapes[0, j] = _clean_shape(table, half, b0, r0, b1, r1, wt, lo + j)
        else:
            shapes[g, 1:w] = shapes[g - 1, 0 : w - 1]
            shapes[g, 0] = _clean_shape(table, half, b0 + g, r0, b1 + g, r1, wt, lo)
        re = im = total = 0.0
        for j in range(w):
            v = shapes[g, j]
            re += v.real * d[j, 0] + v.imag * d[j, 1]
            im += v.real * d[j, 1] - v.imag * d[j, 0]
            total += v.real * v.real + v.imag * v.imag
        overlap[g] = complex(re, im)
        energy[g] = total
    merge_samples = mainlobe / 4
    nearest = math.ceil(merge_samples)
    farthest = math.floor(mainlobe)
    best_gain = 0.0
    close = False  # the best pair's grid delays lie closer than a quarter main lobe
    # Gram entries G[g, h] = sum_j conj(S_g(j)) S_h(j), by diagonals h - g: as S_g(j) = S_{g-1}(j - 1),
    # G[g, h] = G[g - 1, h - 1] + conj(S_g(0)) S_h(0) - conj(S_{g-1}(w - 1)) S_{h-1}(w - 1), one sample
    # into the window and one out; gram[delta] holds the diagonal's last entry.
    gram = work[: 2 * (farthest + 1)]
    for g in range(n_grid):
        bg, eg = overlap[g], energy[g]
        for h in range(g + 1, min(g + farthest, n_grid - 1) + 1):
            delta = h - g
            if g == 0:
                re = im = 0.0
                for j in range(w):
                    x, y = shapes[0, j], shapes[h, j]
                    re += x.real * y.real + x.imag * y.imag
                    im += x.real * y.imag - x.imag * y.real
            else:
                x, y = shapes[g, 0], shapes[h, 0]
                xo, yo = shapes[g - 1, w - 1], shapes[h - 1, w - 1]
                re = (
                    gram[2 * delta]
                    + (x.real * y.real + x.imag * y.imag)
                    - (xo.real * yo.real + xo.imag * yo.imag)
                )
                im = (
                    gram[2 * delta + 1]
                    + (x.real * y.imag - x.imag * y.real)
                    - (xo.real * yo.imag - xo.imag * yo.real)
                )
            gram[2 * delta], gram[2 * delta + 1] = re, im
            c = complex(re, im)
            bh, eh = overlap[h], energy[h]
            det = eg * eh - (re * re + im * im)
            if not det > 1e-9 * eg * eh:
                continue
            cross = bg.conjugate() * c * bh
            gain = (eh * abs(bg) ** 2 + eg * abs(bh) ** 2 - 2 * cross.real) / det
            if gain > best_gain:
                best_gain = gain
                close = h - g < nearest
                pair_t[0], pair_t[1] = first + g, first + h
                pair_a[0] = (eh * bg - c * bh) / det
                pair_a[1] = (eg * bh - c.conjugate() * bg) / det
    if best_gain <= 0.0:
        return NO_PAIR
    t, a = pair_t, pair_a
    _joint_fit_into(
        table, u, half, d, lo, ok, t, a, False, _SPLIT_ITERATIONS, True, rate, 1e-3, 1e-2, work, new_amps
    )
    # To real amplitudes, the phase read as delay: a R(s - tau) with a = |a| exp(i phi) is
    # |a| R(s - tau + phi / rate) to within the envelope's shift (the nearer of the two signs).
    for i in range(2):
        phase = math.atan2(a[i].imag, a[i].real)
        sign = 1.0
        if abs(phase) > math.pi / 2:
            phase -= math.copysign(math.pi, phase)
            sign = -1.0
        t[i] -= phase / rate
        a[i] = sign * abs(a[i])
    cost = _settle_real(table, u, half, d, lo, ok, t, a, work, new_amps)
    best_cost = cost if _pair_plausible(t, a, lo, hi, merge_samples, mainlobe, threshold) else np.inf
    best_t0, best_t1, best_a0, best_a1 = t[0], t[1], a[0], a[1]
    # The other basins are tried only when this fit leaves more in its window than the threshold
    # (an echo's peak power just detectable): on 200 noisy pairs 7 mm apart, each of the 10 whose
    # better fit lay in another basin left 1.3-9.8 times it, 186 of the other 190 under it.
    tries = 3 if cost > threshold else 0
    if tries:
        settled_t = t.copy()
        settled_a = a.copy()
    period = math.pi / rate
    for moved in range(tries):  # the first member, the second, both
        for step in (-period, period):
            t[:] = settled_t
            a[:] = settled_a
            for member in range(2):
                if moved == member or moved == 2:
                    t[member] += step
                    a[member] = -a[member]
            cost = _settle_real(table, u, half, d, lo, ok, t, a, work, new_amps)
            if cost < best_cost and _pair_plausible(t, a, lo, hi, merge_samples, mainlobe, threshold):
                best_cost = cost
                best_t0, best_t1, best_a0, best_a1 = t[0], t[1], a[0], a[1]
    if not np.isfinite(best_cost):
        return MERGED if members == 1 and close else NO_PAIR
    # The members make way for the pair at first_member: the echoes after them move by 2 - members.
    peak_first, peak_last = peaks[first_member], peaks[last_member]
    total = count + 2 - members
    if members == 1:
        for i in range(count, e + 1, -1):
            tofs[i], amps[i], peaks[i], state[i] = tofs[i - 1], amps[i - 1], peaks[i - 1], state[i - 1]
    elif members > 2:
        for i in range(first_member + 2, total):
            j = i + members - 2
            tofs[i], amps[i], peaks[i], state[i] = tofs[j], amps[j], peaks[j], state[j]
    e = first_member
    tofs[e], amps[e], tofs[e + 1], amps[e + 1] = best_t0, best_a0, best_t1, best_a1
    peaks[e], peaks[e + 1] = peak_first, peak_last
    state[e] = state[e + 1] = BORN
    _sort_by_delay(tofs, amps, peaks, state, total)
    return total


@njit(cache=True)
def _refine_echoes(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    rate: float,
    row: NDArray[np.float32],  # (>= 2 n,): real and imaginary parts side by side
    n: int,
    peaks: NDArray[np.int64],
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    state: NDArray[np.int8],  # FREE, BORN or WAIVED
    n_echo: int,
    fit_half: int,
    mainlobe: float,
    grid_b: NDArray[np.int64],
    grid_w: NDArray[np.float64],
    fitted_tofs: NDArray[np.float64],
    fitted_amps: NDArray[np.complex128],
    scratch: _RefineScratch,
    steps: tuple[int, int, int, int, int],  # max_joint, joint_w, complex, real and lone iterations
) -> int:  # pragma: no cover - compiled
    """The batch path's fits from the echoes' first estimates ``tofs``/``amps[:n_echo]``: twice
    each echo refitted at its peak with the others' model taken out (all updated together;
    BORN ones keep theirs), sorted by delay (stable, with ``peaks`` and ``state``), then
    clusters within two main lobes fitted jointly and lone echoes stepped, into
    ``fitted_tofs``/``fitted_amps``. Returns OK, CLOSE (two within a quarter main lobe) or
    TOO_BIG (a cluster beyond the joint fit's reach).

    ``scratch`` is batch_echoes' (new_tofs, new_amps, window, joint_data, joint_valid, joint_t,
    joint_a, joint_work, joint_new), ``steps`` its (max_joint, joint_w, complex_iterations,
    real_iterations, lone_iterations): the same for every call of a batch."""
    new_tofs, new_amps, window, joint_data, joint_valid, joint_t, joint_a, joint_work, joint_new = scratch
    max_joint, joint_w, complex_iterations, real_iterations, lone_iterations = steps
    for _ in range(2):
        _prepare(u, tofs[:n_echo], grid_b, grid_w)
        for e in range(n_echo):
            if state[e] == BORN:
                new_tofs[e], new_amps[e] = tofs[e], amps[e]
                continue
            # An echo none of whose neighbours reaches its window refits to what it is
            # (their model there is exactly zero): it keeps its fit.
            alone = True
            for j in range(n_echo):
                if j != e and abs(peaks[e] - grid_b[j, 0]) <= half + fit_half + 1:
                    alone = False
            if alone:
                new_tofs[e], new_amps[e] = tofs[e], amps[e]
                continue
            new_tofs[e], new_amps[e] = _fit_peak(
                table, u, half, rate, row, n, peaks[e], fit_half, grid_b, grid_w, amps, n_echo, e, window
            )
        tofs[:n_echo] = new_tofs[:n_echo]
        amps[:n_echo] = new_amps[:n_echo]
    # Sort by delay (stable); clusters of echoes within two main lobes are fitted jointly.
    _sort_by_delay(tofs, amps, peaks, state, n_echo)
    status = OK
    for e in range(1, n_echo):
        if tofs[e] - tofs[e - 1] < mainlobe / 4:
            status = CLOSE
    _prepare(u, tofs[:n_echo], grid_b, grid_w)
    fitted_tofs[:n_echo] = tofs[:n_echo]
    fitted_amps[:n_echo] = amps[:n_echo]
    start = 0
    while start < n_echo and status == OK:
        stop = start + 1
        while stop < n_echo and tofs[stop] - tofs[stop - 1] < 2 * mainlobe:
            stop += 1
        size = stop - start
        if (
            size > max_joint
            or math.ceil(tofs[stop - 1]) - math.floor(tofs[start]) + 2 * fit_half + 1 > joint_w
        ):
            status = TOO_BIG
        elif size > 1 or lone_iterations > 0:
            lo = math.floor(tofs[start]) - fit_half
            hi = math.ceil(tofs[stop - 1]) + fit_half + 1
            w = hi - lo
            data = joint_data[:w]
            valid = joint_valid[:w]
            for j in range(w):
                s = lo + j
                data[j, 0] = data[j, 1] = 0.0
                valid[j] = 0 <= s < n
                if valid[j]:
                    other = _model(table, half, grid_b, grid_w, amps, n_echo, s, start, stop)
                    data[j, 0] = row[2 * s] - other.real
                    data[j, 1] = row[2 * s + 1] - other.imag
            t = joint_t[:size]
            a = joint_a[:size]
            t[:] = tofs[start:stop]
            a[:] = amps[start:stop]
            if size > 1:  # a lone echo's delay is phase-refined: it needs no complex steps
                _joint_fit_into(
                    table,
                    u,
                    half,
                    data,
                    lo,
                    valid,
                    t,
                    a,
                    False,
                    complex_iterations,
                    False,
                    0.0,
                    1e-6,
                    0.0,
                    joint_work,
                    joint_new,
                )
            for i in range(size):
                a[i] = abs(a[i]) if a[i].real >= 0 else -abs(a[i])
            if size == 1:
                t[0], a[0] = _lone_fit(table, u, half, data, lo, valid, t[0], a[0], lone_iterations)
            else:
                _joint_fit_into(
                    table,
                    u,
                    half,
                    data,
                    lo,
                    valid,
                    t,
                    a,
                    True,
                    real_iterations,
                    False,
                    0.0,
                    1e-6,
                    0.0,
                    joint_work,
                    joint_new,
                )
            fitted_tofs[start:stop] = t
            fitted_amps[start:stop] = a
        start = stop
    return status


@njit(cache=True)
def _drop_faint(
    fitted_tofs: NDArray[np.float64],
    fitted_amps: NDArray[np.complex128],
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    peaks: NDArray[np.int64],
    state: NDArray[np.int8],  # FREE, BORN or WAIVED
    n_echo: int,
    threshold: float,
    cand_k: NDArray[np.int64],
    accepted: NDArray[np.bool_],
    n_cand: int,
) -> int:  # pragma: no cover - compiled
    """After a split and the refits around it: drop the echoes (not of a pair) that fell below
    the threshold on |a|^2, in place in every array; they stood for what the single echo's model
    left over, and their peaks are checked as rejected candidates' from now on. The new count."""
    kept = 0
    for e in range(n_echo):
        if state[e] != FREE or abs(fitted_amps[e]) ** 2 >= threshold:
            fitted_tofs[kept], fitted_amps[kept] = fitted_tofs[e], fitted_amps[e]
            tofs[kept], amps[kept], peaks[kept], state[kept] = tofs[e], amps[e], peaks[e], state[e]
            kept += 1
            continue
        for j in range(n_cand):
            if accepted[j] and cand_k[j] == peaks[e]:
                accepted[j] = False
    return kept


@njit(cache=True)
def _residual_noise_power(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    row: NDArray[np.float32],  # (>= 2 n,): real and imaginary parts side by side
    n: int,
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    count: int,
    noise_step: int,
    resid: NDArray[np.complex128],
    noise: NDArray[np.float64],
    median_scratch: NDArray[np.float64],  # (3, >= n_noise)
    counts: NDArray[np.int32],  # (_EXPONENT_BUCKETS + _MANTISSA_BUCKETS,)
) -> float:  # pragma: no cover - compiled
    """The noise power of a channel's correlation (``row``, real and imaginary side by side) less
    its echoes' model: ``median |r|^2 / ln 2`` over every ``noise_step``-th lag (the batch path's
    estimate, made on the residual as CLEAN makes its own)."""
    for s in range(n):
        resid[s] = complex(row[2 * s], row[2 * s + 1])
    for e in range(count):
        clean_subtract(table, u, half, resid[:n], tofs[e], amps[e])
    n_noise = (n + noise_step - 1) // noise_step
    for i in range(n_noise):
        value = resid[i * noise_step]
        noise[i] = value.real * value.real + value.imag * value.imag
    median = _noise_median(noise[:n_noise], counts, median_scratch)
    return max(median / math.log(2.0), 1e-300)


_SPLIT_TARGETS = 3
"""Echoes a round of splits tries, the one the checks blame first: the blame goes to the echo
whose two main lobes hold the most misfit against what they allow, and a weak echo beside a
strong pair that merged into one peak allows the least (on the five-reflector bench frames,
the pair's stronger neighbour was blamed in 2 of the 9 channels the first split left to CLEAN)."""


@njit(cache=True)
def _split_targets(
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    state: NDArray[np.int8],
    count: int,
    failed: int,
    mainlobe: float,
    targets: NDArray[np.int64],
) -> int:  # pragma: no cover - compiled
    """The echoes a round of splits tries, into ``targets``: ``failed`` (the one the checks
    blamed), then the other FREE echoes within two main lobes of it, strongest first (stable),
    at most ``len(targets)`` in all (a pair's members are not split again). Returns how many."""
    targets[0] = failed
    found = 1
    for j in range(count):
        if j == failed or state[j] != FREE or abs(tofs[j] - tofs[failed]) >= 2 * mainlobe:
            continue
        # Its place among the neighbours so far (targets[1:found], strongest first; equal ones
        # keep their order), the weakest dropped when they are full.
        magnitude = abs(amps[j])
        place = found
        while place > 1 and abs(amps[targets[place - 1]]) < magnitude:
            place -= 1
        if place == len(targets):
            continue
        for q in range(min(found, len(targets) - 1), place, -1):
            targets[q] = targets[q - 1]
        targets[place] = j
        found = min(found + 1, len(targets))
    return found


@njit(cache=True)
def batch_echoes(
    corr: NDArray[np.float32],  # (n_ch, >= 2 n): complex64 rows viewed as float32
    n: int,
    constants: BatchConstants,
    out_tof: NDArray[np.float64],  # (n_ch, slots)
    out_amp: NDArray[np.float64],  # (n_ch, slots)
    out_count: NDArray[np.int64],
    out_power: NDArray[np.float64],
    out_status: NDArray[np.int64],  # each channel's status (OK, TOO_MANY, ...)
) -> None:  # pragma: no cover - compiled
    """Echoes of every channel of ``corr`` this path can vouch for (echoes._isolated_echoes).

    Clusters of echoes within two main lobes get ``complex_iterations`` and then
    ``real_iterations`` Levenberg-Marquardt steps; a lone echo ``lone_iterations`` real ones.
    An echo the checks find unexplained is split in two (:func:`_split_echo`), at most
    ``max_splits`` times a channel.

    ``corr`` is the complex correlation (n_ch, >= n) viewed as (n_ch, >= 2 n) reals, of
    which the first ``n`` samples of each row are read (the rows of a longer FFT output can
    be passed as they are). ``constants`` are the arguments that stay the same from frame to
    frame (echoes.BatchConstants, a named tuple), read here by name. Scratch is allocated
    once a call, not once a channel.
    """
    table = constants.table
    u = constants.oversample
    half = constants.half_width
    rate = constants.phase_rate_rad_per_lag
    dilated = constants.sidelobe_envelope
    mainlobe = constants.mainlobe_lags
    acf_energy = constants.acf_energy
    threshold_factor = constants.threshold_factor
    dynamic_range = constants.dynamic_range
    first = constants.first_lag
    max_candidates = constants.max_candidates
    residue = constants.residue_lags
    max_joint = constants.max_joint
    complex_iterations = constants.complex_iterations
    real_iterations = constants.real_iterations
    lone_iterations = constants.lone_iterations
    max_splits = constants.max_splits
    noise_step = constants.noise_step
    n_ch = corr.shape[0]
    fit_half = max(1, int(np.round(mainlobe / 2)))
    span = math.ceil(mainlobe)
    power_map = np.zeros(n)
    residual_power = np.zeros(n)  # the checks' |data - model|^2 around each echo
    maxima = np.zeros(n + 1, dtype=np.int64)
    maxima_power = np.zeros(n + 1)
    local_floor = np.zeros(n + 1)
    local_scratch = np.zeros(n + 1)
    queue = np.zeros(n + 1, dtype=np.int64)
    n_noise = (n + noise_step - 1) // noise_step
    noise = np.zeros(n_noise)
    median_scratch = np.zeros((3, n_noise))
    counts = np.zeros(_EXPONENT_BUCKETS + _MANTISSA_BUCKETS, dtype=np.int32)
    cand_k = np.zeros(max_candidates, dtype=np.int64)
    cand_a = np.zeros(max_candidates)
    accepted = np.zeros(max_candidates, dtype=np.bool_)
    peaks = np.zeros(max_candidates, dtype=np.int64)
    tofs = np.zeros(max_candidates)
    amps = np.zeros(max_candidates, dtype=np.complex128)
    new_tofs = np.zeros(max_candidates)
    new_amps = np.zeros(max_candidates, dtype=np.complex128)
    fitted_tofs = np.zeros(max_candidates)
    fitted_amps = np.zeros(max_candidates, dtype=np.complex128)
    grid_b = np.zeros((max_candidates, 4), dtype=np.int64)
    grid_w = np.zeros(max_candidates)
    window = np.zeros(2 * max(fit_half, span) + 1, dtype=np.complex128)
    # A cluster's fit spans at most max_joint echoes two main lobes apart and half a main lobe
    # beyond each end.
    joint_w = math.ceil((max_joint - 1) * 2 * mainlobe) + 2 * fit_half + 4
    # A split's window: its members (within a main lobe and a half of the echo either side), a
    # main lobe either side of them and half a main lobe beyond.
    split_w = 4 * span + 4 * fit_half + 4
    joint_work = np.empty(max(_fit_scratch_size(max_joint, joint_w), _fit_scratch_size(2, split_w)))
    joint_data = np.zeros((joint_w, 2))
    joint_valid = np.zeros(joint_w, dtype=np.bool_)
    joint_t = np.zeros(max_joint)
    joint_a = np.zeros(max_joint, dtype=np.complex128)
    joint_new = np.zeros(max(max_joint, 2), dtype=np.complex128)
    split_grid = 4 * span + 2 * fit_half + 4
    split_data = np.zeros((split_w, 2))
    split_valid = np.ones(split_w, dtype=np.bool_)
    split_shapes = np.zeros((split_grid, split_w), dtype=np.complex128)
    split_overlap = np.zeros(split_grid, dtype=np.complex128)
    split_energy = np.zeros(split_grid)
    split_t = np.zeros(2)
    split_a = np.zeros(2, dtype=np.complex128)
    state = np.zeros(max_candidates, dtype=np.int8)
    resid = np.zeros(n, dtype=np.complex128)
    kept_tofs = np.zeros(max_candidates)
    kept_amps = np.zeros(max_candidates, dtype=np.complex128)
    kept_peaks = np.zeros(max_candidates, dtype=np.int64)
    kept_state = np.zeros(max_candidates, dtype=np.int8)
    kept_accepted = np.zeros(max_candidates, dtype=np.bool_)
    targets = np.zeros(_SPLIT_TARGETS, dtype=np.int64)
    refine_scratch = (
        new_tofs,
        new_amps,
        window,
        joint_data,
        joint_valid,
        joint_t,
        joint_a,
        joint_work,
        joint_new,
    )
    refine_steps = (max_joint, joint_w, complex_iterations, real_iterations, lone_iterations)
    for ch in range(n_ch):
        out_count[ch] = 0
        out_status[ch] = OK
        row = corr[ch]
        for k in range(n):
            re, im = float(row[2 * k]), float(row[2 * k + 1])
            power_map[k] = re * re + im * im
        for i in range(n_noise):
            noise[i] = power_map[i * noise_step]
        noise_median = _noise_median(noise, counts, median_scratch)
        power = max(noise_median / math.log(2.0), 1e-300)
        out_power[ch] = power
        threshold = threshold_factor * power
        # Candidates: local maxima above the threshold, within the dynamic range of the strong
        # echoes around them (_local_floor). The test of a sample above the threshold is
        # branch-free (it is written, the count advances by the test): there the tests are
        # unpredictable, and mispredicted branches cost more than the arithmetic.
        n_cand = 0
        strongest = 0.0
        for k in range(max(first, 1), n - 1):
            pk = power_map[k]
            if pk > threshold:
                local_max = (pk > power_map[k - 1]) & (pk >= power_map[k + 1])
                maxima[n_cand] = k
                n_cand += local_max
                strongest = max(strongest, pk * local_max)
        if n_cand == 0:
            continue
        for i in range(n_cand):
            maxima_power[i] = power_map[maxima[i]]
        _local_floor(maxima, maxima_power, n_cand, residue, local_floor, local_scratch, queue)
        m = 0
        for i in range(n_cand):
            k = maxima[i]
            pk = maxima_power[i]
            if pk >= local_floor[i] * dynamic_range and pk >= strongest * _PRECISION_POWER:
                if m == max_candidates:
                    m += 1
                    break
                cand_k[m] = k
                cand_a[m] = math.sqrt(pk)
                m += 1
        if m > max_candidates:
            out_status[ch] = TOO_MANY
            continue
        _sort_descending(cand_a, cand_k, m)
        # Strongest first, a candidate is an echo unless the accepted echoes' sidelobes explain it.
        n_echo = 0
        for j in range(m):
            bound = 0.0
            for i in range(j):
                if accepted[i]:
                    gap = abs(cand_k[i] - cand_k[j]) + half
                    if gap <= 2 * half:
                        bound += dilated[gap] * cand_a[i]
            accepted[j] = cand_a[j] > 1.5 * bound and cand_a[j] > 0
            if accepted[j]:
                peaks[n_echo] = cand_k[j]
                n_echo += 1
        # Each echo alone, then twice with the others' model taken out (all updated together).
        for e in range(n_echo):
            tofs[e], amps[e] = _fit_peak(
                table, u, half, rate, row, n, peaks[e], fit_half, grid_b, grid_w, amps, 0, 0, window
            )
        state[:n_echo] = FREE
        status = _refine_echoes(
            table,
            u,
            half,
            rate,
            row,
            n,
            peaks,
            tofs,
            amps,
            state,
            n_echo,
            fit_half,
            mainlobe,
            grid_b,
            grid_w,
            fitted_tofs,
            fitted_amps,
            refine_scratch,
            refine_steps,
        )
        if status != OK:
            out_status[ch] = status
            continue
        _prepare(u, fitted_tofs[:n_echo], grid_b, grid_w)
        status, failed = _channel_checks(
            table,
            half,
            row,
            n,
            grid_b,
            grid_w,
            fitted_tofs,
            fitted_amps,
            peaks,
            n_echo,
            cand_k,
            accepted,
            m,
            fit_half,
            span,
            threshold,
            power,
            acf_energy,
            residual_power,
            state,
        )
        # An echo its model leaves unexplained may be two within a main lobe (their main lobes
        # merged into one peak): split it (or, failing that, a neighbour: _split_targets), fit the
        # others again around the pair, and check the channel again; a pair that fails goes to CLEAN.
        splits = 0
        while status != OK and failed >= 0 and state[failed] == FREE and splits < max_splits:
            splits += 1
            kept_n = n_echo
            kept_tofs[:n_echo], kept_amps[:n_echo] = fitted_tofs[:n_echo], fitted_amps[:n_echo]
            kept_peaks[:n_echo], kept_state[:n_echo] = peaks[:n_echo], state[:n_echo]
            kept_accepted[:m] = accepted[:m]
            n_targets = _split_targets(kept_tofs, kept_amps, kept_state, kept_n, failed, mainlobe, targets)
            holds = False
            for attempt in range(2 * n_targets):
                target = targets[attempt // 2]
                # First with the echoes within a main lobe as the pair's other members, then within
                # a main lobe and a half (the pair's interference can put two peaks either side of it).
                reach = mainlobe + (fit_half if attempt % 2 else 0)
                n_echo = kept_n
                fitted_tofs[:n_echo], fitted_amps[:n_echo] = kept_tofs[:n_echo], kept_amps[:n_echo]
                peaks[:n_echo], state[:n_echo] = kept_peaks[:n_echo], kept_state[:n_echo]
                accepted[:m] = kept_accepted[:m]
                _prepare(u, fitted_tofs[:n_echo], grid_b, grid_w)
                outcome = NO_PAIR
                if n_echo < max_candidates:
                    outcome = _split_echo(
                        table,
                        u,
                        half,
                        rate,
                        row,
                        n,
                        fitted_tofs,
                        fitted_amps,
                        peaks,
                        state,
                        n_echo,
                        target,
                        reach,
                        grid_b,
                        grid_w,
                        fit_half,
                        mainlobe,
                        threshold,
                        split_data,
                        split_valid,
                        split_shapes,
                        split_overlap,
                        split_energy,
                        joint_work,
                        joint_new,
                        split_t,
                        split_a,
                    )
                if outcome == NO_PAIR:
                    continue
                if outcome == MERGED:
                    state[target] = WAIVED
                else:
                    # The other echoes fitted again around the pair, from the fits so far.
                    n_echo = outcome
                    tofs[:n_echo] = fitted_tofs[:n_echo]
                    amps[:n_echo] = fitted_amps[:n_echo]
                    refit = _refine_echoes(
                        table,
                        u,
                        half,
                        rate,
                        row,
                        n,
                        peaks,
                        tofs,
                        amps,
                        state,
                        n_echo,
                        fit_half,
                        mainlobe,
                        grid_b,
                        grid_w,
                        fitted_tofs,
                        fitted_amps,
                        refine_scratch,
                        refine_steps,
                    )
                    if refit != OK:
                        continue
                    n_echo = _drop_faint(
                        fitted_tofs,
                        fitted_amps,
                        tofs,
                        amps,
                        peaks,
                        state,
                        n_echo,
                        threshold,
                        cand_k,
                        accepted,
                        m,
                    )
                _prepare(u, fitted_tofs[:n_echo], grid_b, grid_w)
                status, failed = _channel_checks(
                    table,
                    half,
                    row,
                    n,
                    grid_b,
                    grid_w,
                    fitted_tofs,
                    fitted_amps,
                    peaks,
                    n_echo,
                    cand_k,
                    accepted,
                    m,
                    fit_half,
                    span,
                    threshold,
                    power,
                    acf_energy,
                    residual_power,
                    state,
                )
                # The split holds unless the checks still fault the pair (or the merged echo).
                holds = status == OK or (failed >= 0 and state[failed] == FREE)
                if holds:
                    break
            if not holds:
                status = UNEXPLAINED
                break
        out_status[ch] = status
        if status != OK:
            continue
        if splits:
            # A channel crowded enough to need a split has its noise power from what its echoes
            # leave, as CLEAN has: there the correlation's own median holds their sidelobes
            # (4 dB too much on average on the random 1-6 reflector frames, up to 10).
            out_power[ch] = _residual_noise_power(
                table,
                u,
                half,
                row,
                n,
                fitted_tofs,
                fitted_amps,
                n_echo,
                noise_step,
                resid,
                noise,
                median_scratch,
                counts,
            )
        count = min(n_echo, out_tof.shape[1])
        for e in range(count):
            out_tof[ch, e] = fitted_tofs[e]
            out_amp[ch, e] = abs(fitted_amps[e])
        out_count[ch] = count


@njit(cache=True, parallel=True)
def batch_echoes_parallel(
    parts: int,
    corr: NDArray[np.float32],  # (n_ch, >= 2 n): complex64 rows viewed as float32
    n: int,
    constants: BatchConstants,
    out_tof: NDArray[np.float64],  # (n_ch, slots)
    out_amp: NDArray[np.float64],  # (n_ch, slots)
    out_count: NDArray[np.int64],
    out_power: NDArray[np.float64],
    out_status: NDArray[np.int64],
) -> None:  # pragma: no cover - compiled
    """:func:`batch_echoes` on ``parts`` consecutive groups of channels at once, one thread a group.

    Channels are independent, so the answers are those of one call over all of them.
    """
    n_ch = corr.shape[0]
    for part in prange(parts):
        lo, hi = part * n_ch // parts, (part + 1) * n_ch // parts
        batch_echoes(
            corr[lo:hi],
            n,
            constants,
            out_tof[lo:hi],
            out_amp[lo:hi],
            out_count[lo:hi],
            out_power[lo:hi],
            out_status[lo:hi],
        )


@njit(cache=True)
def finish_channels(
    out_tof: NDArray[np.float64],  # (n_ch, slots)
    out_amp: NDArray[np.float64],  # (n_ch, slots)
    out_count: NDArray[np.int64],
    out_power: NDArray[np.float64],
    ok: NDArray[np.bool_],
    lag_rate_hz: float,
    arrival_s: float,
    blanking_s: float,
    threshold_db: float,
    floor_ratio: float,
    support_s: float,
    tof_s: NDArray[np.float64],  # (n_ch, >= slots)
    amplitude: NDArray[np.float64],  # (n_ch, >= slots)
    snr_db: NDArray[np.float64],  # (n_ch, >= slots)
    kept: NDArray[np.int64],
) -> None:  # pragma: no cover - compiled
    """echoes.finish_channel of every channel the batch path fitted: delays in seconds, output
    SNR, blanked, sub-threshold and out-of-range echoes dropped, and those weaker by more than
    the dynamic range (``floor_ratio``) than an echo within ``support_s`` of them; in ascending
    delay (stable)."""
    seconds = np.empty(out_tof.shape[1])
    for ch in range(len(out_count)):
        kept[ch] = 0
        if not ok[ch]:
            continue
        count = out_count[ch]
        strongest = 0.0
        for e in range(count):
            seconds[e] = out_tof[ch, e] / lag_rate_hz + arrival_s
            strongest = max(strongest, out_amp[ch, e])
        m = 0
        for e in range(count):
            t = seconds[e]
            a = out_amp[ch, e]
            snr = 10 * np.log10(max(a * a, 1e-300) / out_power[ch])
            faint = a < strongest * _PRECISION_AMPLITUDE
            for j in range(count):
                # (not >: a delay that is not a number is near every echo, as finish_channel takes it)
                faint |= (not abs(t - seconds[j]) > support_s) and a < out_amp[ch, j] * floor_ratio
            if t >= blanking_s and snr >= threshold_db and not faint and np.isfinite(t):
                # Insertion into the kept echoes, after any of equal delay (a stable sort).
                i = m
                while i > 0 and tof_s[ch, i - 1] > t:
                    tof_s[ch, i] = tof_s[ch, i - 1]
                    amplitude[ch, i] = amplitude[ch, i - 1]
                    snr_db[ch, i] = snr_db[ch, i - 1]
                    i -= 1
                tof_s[ch, i] = t
                amplitude[ch, i] = a
                snr_db[ch, i] = snr
                m += 1
        kept[ch] = m


@njit(cache=True, nogil=True)
def batch_channels(
    parts: int,
    corr: NDArray[np.float32],  # (n_ch, >= 2 n): complex64 rows viewed as float32
    n: int,
    constants: BatchConstants,
    finishing: FinishingConstants,
    out: NDArray[np.float64],  # (3, n_ch, slots)
    kept: NDArray[np.int64],
    ok: NDArray[np.bool_],
) -> None:  # pragma: no cover - compiled
    """:func:`batch_echoes` (on ``parts`` threads: :func:`batch_echoes_parallel`), then
    :func:`finish_channels`, in one call: the channels as ChannelEchoes' arrays. One call, not
    two, for a stream's one-frame calls (each call from Python costs its arguments' unboxing
    and its outputs' allocation).

    ``constants`` are batch_echoes' (echoes.BatchConstants), ``finishing``
    finish_channels' (echoes.FinishingConstants); ``out`` (3, n_ch, slots) takes the
    delays (s), amplitudes and SNRs (dB), ``kept`` their counts and ``ok`` False for the channels
    left to CLEAN.
    """
    n_ch = corr.shape[0]
    slots = out.shape[2]
    out_tof = np.zeros((n_ch, slots))
    out_amp = np.zeros((n_ch, slots))
    out_count = np.zeros(n_ch, dtype=np.int64)
    out_power = np.zeros(n_ch)
    out_status = np.zeros(n_ch, dtype=np.int64)
    if parts == 1:
        batch_echoes(corr, n, constants, out_tof, out_amp, out_count, out_power, out_status)
    else:
        batch_echoes_parallel(parts, corr, n, constants, out_tof, out_amp, out_count, out_power, out_status)
    for ch in range(n_ch):
        ok[ch] = out_status[ch] == OK
    finish_channels(
        out_tof,
        out_amp,
        out_count,
        out_power,
        ok,
        finishing.lag_rate_hz,
        finishing.arrival_s,
        finishing.blanking_s,
        finishing.threshold_db,
        finishing.floor_ratio,
        finishing.support_s,
        out[0],
        out[1],
        out[2],
        kept,
    )


# --- CLEAN (echoes._Clean) -----------------------------------------------------------
#
# The same arithmetic as _Clean's methods, on one channel's double-precision residual
# (complex, modified in place); the components are arrays (delays, complex amplitudes) in
# the order _Clean keeps them in its list, which decides the order of the refits.


@njit(cache=True, inline="always")
def _clean_shape(
    table: NDArray[np.complex128],
    half: int,
    base0: int,
    row0: int,
    base1: int,
    row1: int,
    weight: float,
    s: int,
) -> complex:  # pragma: no cover - compiled
    """_Clean._shape at sample ``s``: ``(1 - w) row0 + w row1``, row1 one lag later past a whole sample."""
    width = 2 * half + 1
    lag0 = s - base0 + half
    lag1 = s - base1 + half
    v0 = 0j
    v1 = 0j
    if lag0 >= 0 and lag0 < width:
        v0 = table[row0, lag0]
    if lag1 >= 0 and lag1 < width:
        v1 = table[row1, lag1]
    return (1 - weight) * v0 + weight * v1


@njit(cache=True)
def clean_subtract(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    values: NDArray[np.complex128],
    tof: float,
    scale: complex,
) -> None:  # pragma: no cover - compiled
    """``values -= scale * R(s - tof)`` over the template's reach (_Clean._shape, then echoes._subtract).

    The interpolation in real arithmetic, ``(1 - w) row0 + w row1`` part by part as numpy
    multiplies a complex row by a real weight (a complex product would cost twice as much).
    """
    b0, r0, b1, r1, w = _grid(u, tof)
    start = b0 - half
    width = 2 * half + 1
    shift = b1 - b0  # row1 is one lag later when the next shift starts the next whole sample
    lo = max(start, 0)
    hi = min(start + width, len(values))
    for s in range(lo, hi):
        lag = s - start
        v0 = table[r0, lag]
        re = (1 - w) * v0.real
        im = (1 - w) * v0.imag
        if lag - shift >= 0:
            v1 = table[r1, lag - shift]
            re += w * v1.real
            im += w * v1.imag
        else:
            re += w * 0.0
            im += w * 0.0
        values[s] -= scale * complex(re, im)


@njit(cache=True, error_model="numpy")  # a zero model divides as numpy does (no exception)
def clean_fit(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    rate: float,
    fit_half: int,
    values: NDArray[np.complex128],
    peak: int,
) -> tuple[float, complex]:  # pragma: no cover - compiled
    """_Clean._fit: delay and complex amplitude of one echo whose envelope peaks at ``peak``."""
    n = len(values)
    lo, hi = max(peak - 1, 0), min(peak + 2, n)
    offset = 0.0
    if hi - lo == 3:
        a, b, c = abs(values[lo]), abs(values[lo + 1]), abs(values[lo + 2])
        denominator = a - 2 * b + c
        if denominator < 0:
            offset = min(max(0.5 * (a - c) / denominator, -0.5), 0.5)
    coarse = peak + offset
    period = math.pi / rate
    weighted = 0.0
    total = 0.0
    for m in range(lo, hi):
        value = values[m]
        magnitude = abs(value)
        estimate = m - math.atan2(value.imag, value.real) / rate
        estimate += period * np.round((coarse - estimate) / period)
        weighted += magnitude**2 * estimate
        total += magnitude**2
    tof = weighted / total if total > 0 else coarse
    if abs(tof - coarse) > 1.5:
        tof = coarse
    b0, r0, b1, r1, w = _grid(u, tof)
    centre = int(np.round(tof))
    num = 0j
    den = 0.0
    for s in range(centre - fit_half, centre + fit_half + 1):
        shape = _clean_shape(table, half, b0, r0, b1, r1, w, s)
        den += shape.real * shape.real + shape.imag * shape.imag
        if 0 <= s < n:
            num += shape.conjugate() * values[s]
    return tof, num / den


@njit(cache=True)
def clean_refit(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    rate: float,
    fit_half: int,
    residual: NDArray[np.complex128],
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    i: int,
) -> None:  # pragma: no cover - compiled
    """_Clean._refit of component ``i``: put it back, fit it again alone, take it out again."""
    n = len(residual)
    clean_subtract(table, u, half, residual, tofs[i], -amps[i])
    centre = int(np.round(tofs[i]))
    lo = max(centre - fit_half, 0)
    hi = min(centre + fit_half + 1, n)
    peak = centre
    if hi > lo:
        peak = lo
        best = abs(residual[lo])
        for s in range(lo + 1, hi):
            magnitude = abs(residual[s])
            if magnitude > best:
                best, peak = magnitude, s
    tofs[i], amps[i] = clean_fit(table, u, half, rate, fit_half, residual, min(max(peak, 0), n - 1))
    clean_subtract(table, u, half, residual, tofs[i], amps[i])


@njit(cache=True)
def clean_extract(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    rate: float,
    fit_half: int,
    cluster_samples: float,
    residual: NDArray[np.complex128],
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    count: int,
    threshold: float,
    floor: float,
    residue: int,
    first: int,
    max_echoes: int,
    refine_passes: int,
) -> int:  # pragma: no cover - compiled
    """_Clean._extract: take echoes out of ``residual`` strongest first; the new number of components.

    ``tofs``/``amps`` hold ``count`` components and room for ``max_echoes``;
    ``threshold`` is the detection threshold on |c|^2 (threshold factor times the noise power);
    ``floor`` the dynamic range as an amplitude ratio, applied within ``residue`` lags of each
    component (_mask_floor).
    """
    n = len(residual)
    strongest = 0.0
    for i in range(count):
        strongest = max(strongest, abs(amps[i]))
    cluster = np.zeros(max_echoes + 1, dtype=np.int64)
    # The search for the strongest sample keeps |c|^2 (0 where the dynamic range masks it) and
    # its maximum per block of samples, refreshed only where a subtraction changed the residual
    # (the template's reach around the echoes fitted, which holds the masks they changed): a
    # scan of every sample per echo was a large share of the extraction's time.
    scan = max(first, 0)
    power = np.zeros(n)
    block = np.zeros(max((n - scan + _BLOCK - 1) // _BLOCK, 0))
    _power_into(residual, power, scan, scan, n)
    _mask_floor(power, scan, n, tofs, amps, count, floor, residue)
    _block_maxima(power, block, scan, scan, n)
    while count < max_echoes:
        # The first strongest sample (its power: the square root is taken once, at the peak).
        peak, top = _strongest(power, block, scan)
        height = abs(residual[peak]) if top > 0 else 0.0
        if height**2 < threshold or height < _PRECISION_AMPLITUDE * strongest:
            break
        tof, amp = clean_fit(table, u, half, rate, fit_half, residual, peak)
        clean_subtract(table, u, half, residual, tof, amp)
        lo, hi = _reach(u, half, tof, n)
        size = 0
        for i in range(count):
            if abs(tofs[i] - tof) < cluster_samples:
                cluster[size] = i
                size += 1
        tofs[count], amps[count] = tof, amp
        cluster[size] = count
        count += 1
        if size:
            for _ in range(refine_passes):
                for j in range(size + 1):
                    before = _reach(u, half, tofs[cluster[j]], n)
                    clean_refit(table, u, half, rate, fit_half, residual, tofs, amps, cluster[j])
                    after = _reach(u, half, tofs[cluster[j]], n)
                    lo, hi = min(lo, before[0], after[0]), max(hi, before[1], after[1])
        # The masks reach past the subtraction (residue >= half): refreshed over their reach.
        lo, hi = max(lo - (residue - half), 0), min(hi + (residue - half), n)
        _power_into(residual, power, scan, lo, hi)
        _mask_floor(power, max(lo, scan), hi, tofs, amps, count, floor, residue)
        _block_maxima(power, block, scan, lo, hi)
        strongest = max(strongest, abs(amps[count - 1]))
    return count


_BLOCK = 64
"""Samples per block of clean_extract's running maxima."""


@njit(cache=True, inline="always")
def _reach(u: int, half: int, tof: float, n: int) -> tuple[int, int]:  # pragma: no cover - compiled
    """The samples ``lo..hi-1`` that clean_subtract changes for an echo at ``tof``."""
    start = _grid(u, tof)[0] - half
    return max(start, 0), min(start + 2 * half + 1, n)


@njit(cache=True)
def _refresh_power(
    residual: NDArray[np.complex128],
    power: NDArray[np.float64],
    block: NDArray[np.float64],
    scan: int,
    lo: int,
    hi: int,
) -> None:  # pragma: no cover - compiled
    """``power = |residual|^2`` over ``lo..hi-1`` (from ``scan`` on), and the maxima of the blocks
    that touch it (block ``b``: samples ``scan + b _BLOCK`` onwards; 0 if nothing is positive)."""
    _power_into(residual, power, scan, lo, hi)
    _block_maxima(power, block, scan, lo, hi)


@njit(cache=True, inline="always")
def _power_into(
    residual: NDArray[np.complex128], power: NDArray[np.float64], scan: int, lo: int, hi: int
) -> None:  # pragma: no cover
    """``power = |residual|^2`` (``re^2 + im^2``) over ``lo..hi-1``, from ``scan`` on."""
    for s in range(max(lo, scan), hi):
        value = residual[s]
        power[s] = value.real * value.real + value.imag * value.imag


@njit(cache=True)
def _mask_floor(
    power: NDArray[np.float64],
    lo: int,
    hi: int,
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    count: int,
    floor: float,
    residue: int,
) -> None:  # pragma: no cover - compiled
    """_Clean._below_floor: ``power`` set to 0 over ``lo..hi-1`` where it is below
    ``(floor |a|)^2`` of a component within ``residue`` lags (``|s - tof| <= residue``): the
    residue and sidelobes of a strong echo, not echoes."""
    for i in range(count):
        tof = tofs[i]
        if not np.isfinite(tof):
            continue
        level = floor * abs(amps[i])
        level = level * level
        for s in range(max(math.ceil(tof - residue), lo), min(math.floor(tof + residue) + 1, hi)):
            if power[s] < level:
                power[s] = 0.0


@njit(cache=True, inline="always")
def _block_maxima(
    power: NDArray[np.float64], block: NDArray[np.float64], scan: int, lo: int, hi: int
) -> None:  # pragma: no cover
    """The maxima of the blocks of ``power`` that touch ``lo..hi-1`` (from ``scan`` on), as
    _refresh_power leaves them."""
    n = len(power)
    lo = max(lo, scan)
    if hi <= lo:
        return
    for b in range((lo - scan) // _BLOCK, (hi - 1 - scan) // _BLOCK + 1):
        top = 0.0
        for s in range(scan + b * _BLOCK, min(scan + (b + 1) * _BLOCK, n)):
            if power[s] > top:
                top = power[s]
        block[b] = top


@njit(cache=True)
def _strongest(
    power: NDArray[np.float64], block: NDArray[np.float64], scan: int
) -> tuple[int, float]:  # pragma: no cover - compiled
    """The first sample of largest positive ``power`` from ``scan`` on, and that power; (0, 0.0) if none
    is positive: the first block of the largest maximum, then its first sample of that power."""
    top = 0.0
    best = -1
    for b in range(len(block)):
        if block[b] > top:
            top, best = block[b], b
    if best < 0:
        return 0, 0.0
    peak = 0
    top = 0.0
    for s in range(scan + best * _BLOCK, min(scan + (best + 1) * _BLOCK, len(power))):
        if power[s] > top:
            top, peak = power[s], s
    return peak, top


@njit(cache=True)
def clean_fit_models(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    fit_half: int,
    restored: NDArray[np.complex128],
    lo: int,
    hi: int,
    fit_tof: NDArray[np.float64],  # (rows, k)
    fit_amp: NDArray[np.complex128],  # (rows, k)
    active: NDArray[np.bool_],  # (rows, k)
    complex_iterations: int,
    real_iterations: int,
    rotation: float,
    tolerance: float,
    gain: float,
    cost: NDArray[np.float64],
) -> None:  # pragma: no cover - compiled
    """_Clean._try_models' fits: each row's active echoes fitted jointly (complex amplitudes,
    then real ones) over its own span on ``restored``, in place, and its cost over lo..hi."""
    n_rows, k = fit_tof.shape
    # Scratch for every row (a row's span lies within lo..hi): allocated once, not per fit.
    t_all = np.zeros(k)
    a_all = np.zeros(k, dtype=np.complex128)
    data_all = np.zeros(2 * (hi - lo))
    valid_all = np.ones(hi - lo, dtype=np.bool_)
    work = np.empty(_fit_scratch_size(k, hi - lo))
    new_amps = np.empty(k, dtype=np.complex128)
    grid_b = np.zeros((k, 4), dtype=np.int64)
    grid_w = np.zeros(k)
    for row in range(n_rows):
        cost[row] = np.inf
        size = 0
        for slot in range(k):
            if active[row, slot]:
                size += 1
        if size == 0:
            continue
        t = t_all[:size]
        a = a_all[:size]
        m = 0
        for slot in range(k):
            if active[row, slot]:
                t[m], a[m] = fit_tof[row, slot], fit_amp[row, slot]
                m += 1
        first = min(max(math.floor(t.min()) - fit_half, lo), hi - 2)
        last = max(min(math.ceil(t.max()) + fit_half + 1, hi), first + 2)
        w = last - first
        data = data_all[: 2 * w].reshape((w, 2))
        for j in range(w):
            data[j, 0] = restored[first + j].real
            data[j, 1] = restored[first + j].imag
        valid = valid_all[:w]
        _joint_fit_into(
            table,
            u,
            half,
            data,
            first,
            valid,
            t,
            a,
            False,
            complex_iterations,
            True,
            rotation,
            tolerance,
            gain,
            work,
            new_amps,
        )
        for i in range(size):
            a[i] = abs(a[i]) if a[i].real >= 0 else -abs(a[i])
        _joint_fit_into(
            table,
            u,
            half,
            data,
            first,
            valid,
            t,
            a,
            True,
            real_iterations,
            True,
            0.0,
            1e-6,
            0.0,
            work,
            new_amps,
        )
        _prepare(u, t, grid_b, grid_w)
        total = 0.0
        for s in range(lo, hi):
            r = restored[s] - _model(table, half, grid_b, grid_w, a, size, s, 0, 0)
            total += r.real * r.real + r.imag * r.imag
        cost[row] = total
        m = 0
        for slot in range(k):
            if active[row, slot]:
                fit_tof[row, slot], fit_amp[row, slot] = t[m], a[m]
                m += 1


@njit(cache=True)
def _clean_plausible(
    tofs: NDArray[np.float64], amps: NDArray[np.complex128], mainlobe: float
) -> bool:  # pragma: no cover - compiled
    """_Clean._plausible: no two echoes within a main lobe of opposite signs, or one below a
    quarter of its neighbour."""
    order = np.argsort(tofs, kind="mergesort")
    for i in range(len(order) - 1):
        first, second = order[i], order[i + 1]
        if tofs[second] - tofs[first] >= mainlobe:
            continue
        a, b = amps[first].real, amps[second].real
        if a * b < 0 or min(abs(a), abs(b)) < 0.25 * max(abs(a), abs(b)):
            return False
    return True


@njit(cache=True)
def _clean_window_cost(
    values: NDArray[np.complex128], lo: int, hi: int
) -> float:  # pragma: no cover - compiled
    """_Clean._window_cost: ``sum |values[lo:hi]|^2``."""
    total = 0.0
    for s in range(lo, hi):
        total += values[s].real * values[s].real + values[s].imag * values[s].imag
    return total


@njit(cache=True)
def clean_try_models(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    fit_half: int,
    mainlobe: float,
    merge_samples: float,
    acf_energy: float,
    threshold: float,
    residual: NDArray[np.complex128],
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    count: int,
    start_tof: NDArray[np.float64],  # (rows, k)
    start_amp: NDArray[np.complex128],  # (rows, k)
    active: NDArray[np.bool_],  # (rows, k)
    split: bool,
    complex_iterations: int,
    real_iterations: int,
    rotation: float,
    tolerance: float,
    gain: float,
) -> int:  # pragma: no cover - compiled
    """_Clean._try_models of the group ``tofs``/``amps[:count]`` (sorted by delay) against the
    candidate rows (``start_tof``/``start_amp``/``active``); ``split``: keep only fits with more
    echoes than the group, none below a quarter of the strongest (_choose_order's ``keep``).

    The winner replaces the group in ``residual`` and in ``tofs``/``amps`` (sorted by delay; room
    for the largest candidate); returns its size, or -1 when the group stays.
    """
    n = len(residual)
    n_rows, k = start_tof.shape
    span = math.ceil(mainlobe)
    lo = max(math.floor(tofs[:count].min()) - span, 0)
    hi = min(math.ceil(tofs[:count].max()) + span + 1, n)
    if n_rows == 0 or hi - lo < 2:
        return -1
    penalty = 0.5 * threshold * acf_energy
    restored = residual.copy()
    for i in range(count):  # the data: the residual with the group put back
        clean_subtract(table, u, half, restored, tofs[i], -amps[i])
    fit_tof = start_tof.copy()
    fit_amp = start_amp.copy()
    cost = np.empty(n_rows)
    clean_fit_models(
        table,
        u,
        half,
        fit_half,
        restored,
        lo,
        hi,
        fit_tof,
        fit_amp,
        active,
        complex_iterations,
        real_iterations,
        rotation,
        tolerance,
        gain,
        cost,
    )
    best_score = _clean_window_cost(residual, lo, hi) + penalty * count
    if not _clean_plausible(tofs[:count], amps[:count], mainlobe):
        best_score = np.inf  # any plausible candidate replaces it
    best_row = -1
    best_size = 0
    t = np.empty(k)
    a = np.empty(k, dtype=np.complex128)
    best_t = np.empty(k)
    best_a = np.empty(k, dtype=np.complex128)
    for row in range(n_rows):
        size = 0
        for slot in range(k):
            if active[row, slot]:
                t[size], a[size] = fit_tof[row, slot], fit_amp[row, slot].real
                size += 1
        score = cost[row] + penalty * size
        if not score < best_score - 1e-12:
            continue  # it could not replace the best so far, valid or not
        order = np.argsort(t[:size], kind="mergesort")
        ts, amp = t[:size][order], a[:size][order]
        ok = np.isfinite(cost[row])
        strongest, weakest = 0.0, np.inf
        for i in range(size):
            magnitude = abs(amp[i])
            strongest, weakest = max(strongest, magnitude), min(weakest, magnitude)
            if magnitude**2 < threshold or not lo <= ts[i] < hi:
                ok = False
            if i and ts[i] - ts[i - 1] < merge_samples:
                ok = False
        if split and not (size > count and weakest >= 0.25 * strongest):
            ok = False
        if not ok or not _clean_plausible(ts, amp, mainlobe):
            continue
        best_row, best_score, best_size = row, score, size
        best_t[:size], best_a[:size] = ts, amp
    if best_row < 0:
        return -1
    residual[:] = restored
    for i in range(best_size):
        tofs[i], amps[i] = best_t[i], best_a[i]
        clean_subtract(table, u, half, residual, tofs[i], amps[i])
    return best_size


@njit(cache=True)
def _candidate(
    start_tof: NDArray[np.float64],  # (rows, k)
    start_amp: NDArray[np.complex128],  # (rows, k)
    active: NDArray[np.bool_],  # (rows, k)
    row: int,
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    count: int,
    skip: int,
) -> int:  # pragma: no cover - compiled
    """Write the group ``tofs``/``amps[:count]`` without member ``skip`` (-1: none) as candidate ``row``;
    its size."""
    slot = 0
    for j in range(count):
        if j != skip:
            start_tof[row, slot], start_amp[row, slot] = tofs[j], amps[j]
            active[row, slot] = True
            slot += 1
    return slot


@njit(cache=True)
def clean_choose_order(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    rate: float,
    fit_half: int,
    mainlobe: float,
    merge_samples: float,
    acf_energy: float,
    threshold: float,
    power: float,
    residual: NDArray[np.complex128],
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    count: int,
    complex_iterations: int,
    real_iterations: int,
    tolerance: float,
    gain: float,
) -> int:  # pragma: no cover - compiled
    """_Clean._choose_order (with _choose_overlapping) of the group ``tofs``/``amps[:count]``,
    sorted by delay, on ``residual``, in place: the chosen model into ``tofs``/``amps`` (room for
    ``max(count, 2)``), its size returned. ``threshold`` is on |a|^2 (the factor times ``power``)."""
    n = len(residual)
    if count == 0:
        return 0
    if count == 1:
        # The split test: the stretch holds one echo more than CLEAN found?
        span = math.ceil(mainlobe)
        lo = max(math.floor(tofs[0]) - span, 0)
        hi = min(math.ceil(tofs[0]) + span + 1, n)
        base_cost = _clean_window_cost(residual, lo, hi)
        echo_energy = abs(amps[0]) ** 2 * acf_energy
        if base_cost < 3.0 * power * (hi - lo) or base_cost < 0.003 * echo_energy:
            return count
        quarter = mainlobe / 4
        start_tof = np.zeros((2, 2))
        start_amp = np.zeros((2, 2), dtype=np.complex128)
        active = np.ones((2, 2), dtype=np.bool_)
        for row, offset in enumerate((quarter, 2 * quarter)):
            start_tof[row, 0], start_tof[row, 1] = tofs[0] - offset, tofs[0] + offset
            start_amp[row, 0] = start_amp[row, 1] = amps[0] / 2
        new = clean_try_models(
            table,
            u,
            half,
            fit_half,
            mainlobe,
            merge_samples,
            acf_energy,
            threshold,
            residual,
            tofs,
            amps,
            count,
            start_tof,
            start_amp,
            active,
            True,
            complex_iterations,
            real_iterations,
            rate,
            tolerance,
            gain,
        )
        return count if new < 0 else new
    # _choose_overlapping: only where main lobes overlap by more than half.
    delays = np.sort(tofs[:count])
    close = False
    for i in range(count - 1):
        close |= delays[i + 1] - delays[i] < mainlobe
    if not close:
        return count
    period = math.pi / rate
    # The whole stretch read afresh as two echoes either side of its centroid.
    weights = 0.0
    weighted = 0.0
    total = 0.0
    for i in range(count):
        weight = abs(amps[i]) ** 2
        weights += weight
        weighted += weight * tofs[i]
        total += abs(amps[i])
    centroid = weighted / max(weights, 1e-300)
    half_amplitude = complex(total / 2)
    for round_ in range(count):
        g = count
        # Rows: each member moved by half a cycle either way; the rest without it (if any); the
        # rest with one other moved either way (if two or more remain); the fresh pair first.
        per_member = 2 + (1 if g > 1 else 0) + (2 * (g - 1) if g > 2 else 0)
        rows = (2 if round_ == 0 else 0) + g * per_member
        k = max(g, 2) if round_ == 0 else g
        start_tof = np.full((rows, k), tofs[0])
        start_amp = np.zeros((rows, k), dtype=np.complex128)
        active = np.zeros((rows, k), dtype=np.bool_)
        row = 0
        if round_ == 0:
            for offset in (mainlobe / 4, mainlobe / 2):
                start_tof[row, 0], start_tof[row, 1] = centroid - offset, centroid + offset
                start_amp[row, 0] = start_amp[row, 1] = half_amplitude
                active[row, 0] = active[row, 1] = True
                row += 1
        for i in range(g):
            for step in (-period, period):
                _candidate(start_tof, start_amp, active, row, tofs, amps, g, -1)
                start_tof[row, i] += step
                start_amp[row, i] = -amps[i]
                row += 1
            if g > 1:
                rest = row
                size = _candidate(start_tof, start_amp, active, row, tofs, amps, g, i)
                row += 1
                if size > 1:
                    for j in range(size):
                        for step in (-period, period):
                            _candidate(start_tof, start_amp, active, row, tofs, amps, g, i)
                            start_tof[row, j] = start_tof[rest, j] + step
                            start_amp[row, j] = -start_amp[rest, j]
                            row += 1
        new = clean_try_models(
            table,
            u,
            half,
            fit_half,
            mainlobe,
            merge_samples,
            acf_energy,
            threshold,
            residual,
            tofs,
            amps,
            count,
            start_tof,
            start_amp,
            active,
            False,
            complex_iterations,
            real_iterations,
            rate,
            tolerance,
            gain,
        )
        if new < 0:
            break
        count = new
    return count


@njit(cache=True)
def _select(
    a: NDArray[np.float64], k: int, below: NDArray[np.float64], above: NDArray[np.float64]
) -> float:  # pragma: no cover - compiled
    """The ``k``-th smallest of ``a`` (from 0) by quickselect; ``a`` is overwritten (not a
    permutation of itself after), ``below`` and ``above`` are scratch at least as long.

    The partitions are branch-free (every element is written, the write position advances
    by the comparison): on noise the comparisons are unpredictable, and a quickselect that
    branches on them spends most of its time in mispredicted branches.
    """
    lo, hi = 0, len(a)
    while True:
        size = hi - lo
        if size == 1:
            return float(a[lo])
        x, y, z = a[lo], a[lo + size // 2], a[hi - 1]
        pivot = max(min(x, y), min(max(x, y), z))
        n_below = 0
        n_above = 0
        for i in range(lo, hi):
            v = a[i]
            below[n_below] = v
            n_below += v < pivot
            above[n_above] = v
            n_above += v > pivot
        if k < lo + n_below:
            a[lo : lo + n_below] = below[:n_below]
            hi = lo + n_below
        elif k >= hi - n_above:
            a[hi - n_above : hi] = above[:n_above]
            lo = hi - n_above
        else:
            return float(pivot)


@njit(cache=True)
def _median_sampled(values: NDArray[np.float64]) -> float:  # pragma: no cover - compiled
    """:func:`_median`, exactly, in less time on thousands of values.

    Every 8th value brackets the median: its order statistics 1.5 sqrt(m) + 2 either side of
    its own median (m values; the median's rank among them strays by sqrt(m) / 2) are the
    bounds of a band that one pass over the values counts and collects (a fifth of them), and
    the middle values are selected in the band. If they do not lie in it, :func:`_median`.
    """
    n = len(values)
    if n < 1024:
        return _median(values)
    m = n // 8
    sub = np.empty(m)
    for i in range(m):
        sub[i] = values[8 * i]
    band = np.empty(n)
    below = np.empty(n)
    above = np.empty(n)
    margin = int(1.5 * math.sqrt(m)) + 2
    low = _select(sub.copy(), max(m // 2 - margin, 0), below, above)
    high = _select(sub, min(m // 2 + margin, m - 1), below, above)
    n_low = 0
    n_band = 0
    n_high = 0
    for i in range(n):
        v = values[i]
        band[n_band] = v
        n_band += (v >= low) & (v <= high)
        n_low += v < low
        n_high += v > high
    k = n // 2  # the upper middle value; with an even count also the one below it
    first = k - 1 if n % 2 == 0 else k
    if n_low + n_band + n_high != n or not n_low <= first or not k < n_low + n_band:
        return _median(values)  # the middle is outside the band (or a value is NaN)
    upper = _select(band[:n_band].copy(), k - n_low, below, above)
    if n % 2:
        return upper
    # The other middle value is in the band: at least one band value ranks below k.
    return _mean_of_middles(band[:n_band], upper, n_low, k)


@njit(cache=True)
def _clean_noise_power(residual: NDArray[np.complex128]) -> float:  # pragma: no cover - compiled
    """_Clean._noise_power: ``median(re^2 + im^2) / ln 2``, at least the smallest normal float (the
    median exact, and free of the mispredicted branches that slow numpy's)."""
    n = len(residual)
    power = 0.0
    if n:
        values = np.empty(n)
        for s in range(n):
            values[s] = residual[s].real * residual[s].real + residual[s].imag * residual[s].imag
        power = _median_sampled(values) / math.log(2.0)
    return power if power > 0 else 2.2250738585072014e-308


@njit(cache=True)
def _clean_joint_fit(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    fit_half: int,
    merge_samples: float,
    threshold: float,
    residual: NDArray[np.complex128],
    tofs: NDArray[np.float64],
    amps: NDArray[np.complex128],
    count: int,
    complex_iterations: int,
    real_iterations: int,
    rotation: float,
    tolerance: float,
    gain: float,
) -> int:  # pragma: no cover - compiled
    """_Clean._joint_fit of the cluster ``tofs``/``amps[:count]``, in place (sorted by delay); the
    number of echoes kept. ``threshold`` is on |a|^2."""
    n = len(residual)
    for i in range(count):
        clean_subtract(table, u, half, residual, tofs[i], -amps[i])
    order = np.argsort(tofs[:count], kind="mergesort")
    members_t = tofs[:count][order]
    members_a = amps[:count][order]
    size = count
    for _ in range(count):
        lo = max(math.floor(members_t[0]) - fit_half, 0)
        hi = min(math.ceil(members_t[size - 1]) + fit_half + 1, n)
        w = hi - lo
        data = np.empty((w, 2))
        for j in range(w):
            data[j, 0] = residual[lo + j].real
            data[j, 1] = residual[lo + j].imag
        valid = np.ones(w, dtype=np.bool_)
        t = members_t[:size].copy()
        a = members_a[:size].copy()
        joint_fit(
            table, u, half, data, lo, valid, t, a, False, complex_iterations, True, rotation, tolerance, gain
        )
        for i in range(size):
            a[i] = abs(a[i]) if a[i].real >= 0 else -abs(a[i])
        joint_fit(table, u, half, data, lo, valid, t, a, True, real_iterations, True, 0.0, 1e-6, 0.0)
        runaway = False
        for i in range(size):
            runaway |= not (np.isfinite(t[i]) and abs(t[i] - (lo + hi) / 2) < hi - lo)
        if runaway:
            break  # a fit that ran away from its window keeps what successive refinement found
        fitted = np.argsort(t, kind="mergesort")
        kept = 0
        for i in fitted:
            amplitude = a[i].real
            if not (abs(amplitude) ** 2 >= threshold and lo <= t[i] < hi):
                continue
            if kept and t[i] - members_t[kept - 1] < merge_samples:
                if abs(amplitude) > abs(members_a[kept - 1]):
                    members_t[kept - 1], members_a[kept - 1] = t[i], amplitude
                continue
            members_t[kept], members_a[kept] = t[i], amplitude
            kept += 1
        done = kept == size or kept == 0
        size = kept
        if done:
            break
    for i in range(size):
        tofs[i], amps[i] = members_t[i], members_a[i]
        clean_subtract(table, u, half, residual, tofs[i], amps[i])
    return size


@njit(cache=True, nogil=True)
def clean_run(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    rate: float,
    fit_half: int,
    mainlobe: float,
    residue: int,
    merge_samples: float,
    cluster_samples: float,
    acf_energy: float,
    threshold_factor: float,
    floor: float,
    first: int,
    max_echoes: int,
    refine_passes: int,
    complex_iterations: int,
    real_iterations: int,
    tolerance: float,
    gain: float,
    residual: NDArray[np.complex128],
    out_tof: NDArray[np.float64],  # (>= 2 max_echoes,)
    out_amp: NDArray[np.complex128],  # (>= 2 max_echoes,)
    out_power: NDArray[np.float64],  # (1,)
) -> int:  # pragma: no cover - compiled
    """_Clean.run on ``residual`` (the channel's correlation, taken apart in place): the echoes
    into ``out_tof``/``out_amp`` (room for ``2 max_echoes``), the noise power into ``out_power[0]``;
    returns how many echoes."""
    tofs = np.zeros(max(max_echoes, 1))
    amps = np.zeros(max(max_echoes, 1), dtype=np.complex128)
    power = _clean_noise_power(residual)
    args = (table, u, half, rate, fit_half, cluster_samples, residual, tofs, amps)
    count = clean_extract(
        *args, 0, threshold_factor * power, floor, residue, first, max_echoes, refine_passes
    )
    # The first noise estimate includes the echoes' sidelobes; redo it on the residual.
    power = _clean_noise_power(residual)
    count = clean_extract(
        *args, count, threshold_factor * power, floor, residue, first, max_echoes, refine_passes
    )
    out_power[0] = power
    threshold = threshold_factor * power
    # _merge_close: fuse components closer than a quarter main lobe (one echo CLEAN split).
    order = np.argsort(tofs[:count], kind="mergesort")
    sorted_t = tofs[:count][order]
    sorted_a = amps[:count][order]
    merged = 0
    for i in range(count):
        if merged and sorted_t[i] - tofs[merged - 1] < merge_samples:
            clean_subtract(table, u, half, residual, tofs[merged - 1], -amps[merged - 1])
            clean_subtract(table, u, half, residual, sorted_t[i], -sorted_a[i])
            if abs(sorted_a[i]) > abs(amps[merged - 1]):
                tofs[merged - 1] = sorted_t[i]
            amps[merged - 1] = 0j
            clean_refit(table, u, half, rate, fit_half, residual, tofs, amps, merged - 1)
            continue
        tofs[merged], amps[merged] = sorted_t[i], sorted_a[i]
        merged += 1
    # _clusters (a stable sort by delay, chained closer than cluster_samples), each fitted jointly
    # where main lobes overlap by more than half, then its model chosen.
    order = np.argsort(tofs[:merged], kind="mergesort")
    sorted_t = tofs[:merged][order]
    sorted_a = amps[:merged][order]
    group_t = np.zeros(max(merged, 2))
    group_a = np.zeros(max(merged, 2), dtype=np.complex128)
    found = 0
    start = 0
    while start < merged:
        stop = start + 1
        while stop < merged and sorted_t[stop] - sorted_t[stop - 1] < cluster_samples:
            stop += 1
        size = stop - start
        group_t[:size] = sorted_t[start:stop]
        group_a[:size] = sorted_a[start:stop]
        if size > 1:
            close = False
            for i in range(start, stop - 1):
                close |= sorted_t[i + 1] - sorted_t[i] < mainlobe
            if close:
                size = _clean_joint_fit(
                    table,
                    u,
                    half,
                    fit_half,
                    merge_samples,
                    threshold,
                    residual,
                    group_t,
                    group_a,
                    size,
                    complex_iterations,
                    real_iterations,
                    rate,
                    tolerance,
                    gain,
                )
        size = clean_choose_order(
            table,
            u,
            half,
            rate,
            fit_half,
            mainlobe,
            merge_samples,
            acf_energy,
            threshold,
            power,
            residual,
            group_t,
            group_a,
            size,
            complex_iterations,
            real_iterations,
            tolerance,
            gain,
        )
        out_tof[found : found + size] = group_t[:size]
        out_amp[found : found + size] = group_a[:size]
        found += size
        start = stop
    return found


@njit(cache=True, parallel=True, nogil=True)
def clean_run_rows(
    table: NDArray[np.complex128],
    u: int,
    half: int,
    rate: float,
    fit_half: int,
    mainlobe: float,
    residue: int,
    merge_samples: float,
    cluster_samples: float,
    acf_energy: float,
    threshold_factor: float,
    floor: float,
    first: int,
    max_echoes: int,
    refine_passes: int,
    complex_iterations: int,
    real_iterations: int,
    tolerance: float,
    gain: float,
    residuals: NDArray[np.complex128],  # (n_rows, n)
    out_tof: NDArray[np.float64],  # (n_rows, >= 2 max_echoes)
    out_amp: NDArray[np.complex128],  # (n_rows, >= 2 max_echoes)
    out_power: NDArray[np.float64],
    out_count: NDArray[np.int64],
) -> None:  # pragma: no cover - compiled
    """:func:`clean_run` on every row of ``residuals`` (n_rows, n), rows spread over the threads:
    row r's echoes into ``out_tof[r]``/``out_amp[r]``, its noise power into ``out_power[r]`` and
    their number into ``out_count[r]``. Rows are independent: the answers of one call a row."""
    for r in prange(residuals.shape[0]):
        out_count[r] = clean_run(
            table,
            u,
            half,
            rate,
            fit_half,
            mainlobe,
            residue,
            merge_samples,
            cluster_samples,
            acf_energy,
            threshold_factor,
            floor,
            first,
            max_echoes,
            refine_passes,
            complex_iterations,
            real_iterations,
            tolerance,
            gain,
            residuals[r],
            out_tof[r],
            out_amp[r],
            out_power[r : r + 1],
        )
