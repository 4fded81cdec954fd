"""The numpy/scipy statement of the batch path's split of an unexplained echo
(``echoloc.tof._echoes_kernels._split_echo``): which two echoes, within a main lobe of it,
best explain the matched filter's correlation there, and whether the pair is kept.

A test-only oracle: ``tests/tof/test_split_echo.py`` holds the compiled kernel to it. It
lives with the tests, out of the installed package, and is written from the definitions,
not from the kernel's loops:

- the model of an echo at delay ``tau`` is ``a R(s - tau)``, ``R`` the template's analytic
  autocorrelation, evaluated here at any fractional delay by its Fourier sum (the kernel
  interpolates linearly between the rows of a table tabulated 256 times a lag);
- the pair's start is the global least-squares pair with complex amplitudes, found by
  brute force over a quarter-lag grid of delay pairs (closed-form amplitudes at each) and
  polished by ``scipy.optimize.least_squares`` (the kernel: a whole-lag grid through a Gram
  recurrence, then its own Levenberg-Marquardt);
- the real-amplitude fits are ``scipy.optimize.least_squares`` run to convergence (the
  kernel stops its Levenberg-Marquardt once a step gains under 0.1 % of the cost);
- the choice among the half-cycle basins and the plausibility rules are stated as the kernel
  defines them (they are the statement, not a method).

Units: delays and windows are in lags of the correlation, one lag being ``decimation``
samples, i.e. ``decimation / sample_rate_hz`` seconds (lag k of the correlation is a delay of
k lags from the emission start, :meth:`echoloc.tof.echoes.MatchedFilter.correlate`).
Amplitudes are in the correlation's units (an echo ``a * template`` peaks at ``a``); powers
and costs in their squares.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
import scipy.fft
import scipy.optimize
from numpy.typing import NDArray

Outcome = Literal["split", "merged", "no_pair"]


class AcfModel:
    """The template's analytic autocorrelation ``R(x)`` at fractional lags ``x``.

    ``R(x) = sum_k c_k |W_k|^2 exp(2 pi i k D x / N) / (E N)`` over the rfft bins ``k`` of the
    template zero-padded to ``N`` (= ``n_fft``) samples, ``c_k`` the analytic weights (1 at DC and
    Nyquist, 2 between), ``E`` the template's energy and ``D`` the decimation (a lag is ``D``
    samples): the circular analytic autocorrelation, so ``R(0) = 1``. At whole lags it is row 0
    of :attr:`echoloc.tof.echoes.MatchedFilter.acf_table`; between them it is the band-limited
    function itself, not an interpolation.
    """

    def __init__(self, template: NDArray[np.float64], n_fft: int, decimation: int) -> None:
        template = np.asarray(template, dtype=float)
        spectrum = scipy.fft.rfft(template, n_fft)
        weights = np.full(len(spectrum), 2.0)
        weights[0] = 1.0
        if n_fft % 2 == 0:
            weights[-1] = 1.0
        power = np.abs(spectrum) ** 2
        self.coefficients = weights * power / (float(np.sum(template**2)) * n_fft)
        self.frequencies = np.arange(len(spectrum)) * decimation / n_fft  # cycles per lag
        # The carrier's rate: d(arg R)/dx at 0, 2 pi times the power-weighted mean frequency.
        self.rate_rad_per_lag = float(2 * np.pi * np.sum(self.frequencies * power) / np.sum(power))

    def at(self, x: NDArray[np.float64]) -> NDArray[np.complex128]:
        """``R(x)`` at lags ``x`` (any shape)."""
        x = np.asarray(x, dtype=float)
        phases = np.exp(2j * np.pi * np.multiply.outer(x, self.frequencies))
        return np.asarray(phases @ self.coefficients)

    def window(self, lo: int, hi: int) -> _Window:
        """The model's shapes on lags ``lo..hi-1``, for fast evaluation at many delays."""
        return _Window(self, np.arange(lo, hi))


class _Window:
    """``R(s - tau)`` and its derivative in ``tau`` over fixed whole lags ``s``:
    ``exp(2 pi i f (s - tau)) = exp(2 pi i f s) exp(-2 pi i f tau)``, so each delay costs one
    vector of exponentials and a matrix product."""

    def __init__(self, model: AcfModel, lags: NDArray[np.int64]) -> None:
        self.lags = lags
        self.frequencies = model.frequencies
        self.basis = np.exp(2j * np.pi * np.multiply.outer(lags, model.frequencies)) * model.coefficients

    def shapes(self, tau: NDArray[np.float64]) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
        """``R(s - tau_k)`` (k, w) and ``d/dtau_k R(s - tau_k)`` (k, w) for delays ``tau`` (k,), lags."""
        turn = np.exp(-2j * np.pi * np.multiply.outer(np.asarray(tau, dtype=float), self.frequencies))
        values = turn @ self.basis.T
        slopes = (turn * (-2j * np.pi * self.frequencies)) @ self.basis.T
        return values, slopes


class Candidate(NamedTuple):
    """One real-amplitude pair the statement settles.

    tofs, amplitudes
        Delays (lags, ascending) and real amplitudes.
    cost
        The residual energy ``sum |data - model|^2`` over the window.
    plausible
        :func:`pair_plausible`.
    tof_spread, amplitude_spread
        How far each delay (lags) and amplitude may move for the cost to rise by the cost
        itself: ``sqrt(cost (J^T J)^-1_ii)``, the fit's conditioning (``J`` the Jacobian of the
        residual at the minimum). A fit stopped where its cost is ``1 + g`` times the minimum's
        lies within ``sqrt(g)`` of these of it.
    """

    tofs: NDArray[np.float64]
    amplitudes: NDArray[np.float64]
    cost: float
    plausible: bool
    tof_spread: NDArray[np.float64]
    amplitude_spread: NDArray[np.float64]


@dataclass(frozen=True)
class SplitReference:
    """What the statement says of a split.

    outcome
        ``"split"``: the members (the target and the echoes within ``reach`` of it) are replaced
        by ``chosen``; ``"merged"``: no plausible pair, the target stands alone and the whole-lag
        search's best pair lay fewer than ``ceil(mainlobe / 4)`` lags apart (too close for CLEAN
        to resolve); ``"no_pair"``: no plausible pair otherwise.
    chosen
        The kept pair (None unless split).
    lo, hi
        The window, lags ``lo..hi-1``.
    first_member, last_member
        The members' indices among the echoes (inclusive).
    complex_tofs, complex_amplitudes
        The complex-amplitude stage's optimum (lags; complex amplitudes).
    grid_tofs
        The best pair of the search on whole lags, the one ``close`` reads (lags).
    close
        Whether ``grid_tofs`` lie fewer than ``ceil(mainlobe / 4)`` lags apart.
    grid_gap
        How much less energy (a fraction of the best pair's) the best whole-lag pair of the
        other kind (close or not) removes: small, ``close`` hangs on rounding.
    first
        The real-amplitude fit from the complex stage.
    moves
        The six fits from ``first`` moved by half a carrier cycle, sign flipped (first member
        earlier, later; second earlier, later; both earlier, later), always computed here;
        they compete only when ``tried_moves``.
    tried_moves
        Whether ``first`` leaves more than the threshold in the window (``first.cost >
        threshold``), so that the moves compete.
    """

    outcome: Outcome
    chosen: Candidate | None
    lo: int
    hi: int
    first_member: int
    last_member: int
    complex_tofs: NDArray[np.float64]
    complex_amplitudes: NDArray[np.complex128]
    grid_tofs: NDArray[np.float64]
    close: bool
    grid_gap: float
    first: Candidate | None
    moves: tuple[Candidate, ...]
    tried_moves: bool

    @property
    def members(self) -> int:
        """How many echoes the pair would replace."""
        return self.last_member - self.first_member + 1

    def candidates(self) -> tuple[Candidate, ...]:
        """The fits that compete: ``first``, and the moves when tried."""
        if self.first is None:
            return ()
        return (self.first, *self.moves) if self.tried_moves else (self.first,)


def pair_plausible(
    tofs: NDArray[np.float64],
    amplitudes: NDArray[np.float64],
    lo: int,
    hi: int,
    mainlobe_lags: float,
    threshold: float,
) -> bool:
    """Whether a fitted pair is one CLEAN's model choice would keep: both delays finite and in the
    window ``[lo, hi)`` (lags), both amplitudes at the threshold or above (``a^2 >= threshold``,
    a power), at least a quarter main lobe apart, and, when closer than a main lobe, of one sign
    with neither below a quarter of the other (:meth:`echoloc.tof.echoes._Clean._plausible`)."""
    t = np.asarray(tofs, dtype=float)
    a = np.real(np.asarray(amplitudes))
    if not (np.all(np.isfinite(t)) and np.all((lo <= t) & (t < hi)) and np.all(a**2 >= threshold)):
        return False
    separation = abs(t[1] - t[0])
    if separation < mainlobe_lags / 4:
        return False
    if separation < mainlobe_lags:
        return bool(a[0] * a[1] >= 0 and np.min(np.abs(a)) >= 0.25 * np.max(np.abs(a)))
    return True


def choose(candidates: tuple[Candidate, ...], members: int, close: bool) -> tuple[Outcome, Candidate | None]:
    """The decision among settled pairs: the plausible one of least cost is kept; with none,
    ``"merged"`` for a lone target whose whole-lag pair was ``close``, else ``"no_pair"``."""
    plausible = [c for c in candidates if c.plausible]
    if plausible:
        return "split", min(plausible, key=lambda c: c.cost)
    return ("merged" if members == 1 and close else "no_pair"), None


def split_echo_reference(
    correlation: NDArray[np.complexfloating],
    tofs: NDArray[np.float64],
    amplitudes: NDArray[np.complexfloating],
    target: int,
    reach_lags: float,
    model: AcfModel,
    mainlobe_lags: float,
    threshold: float,
    search_step_lags: float = 0.25,
) -> SplitReference:
    """The statement of ``_split_echo``: echo ``target`` of ``tofs``/``amplitudes`` (lags, sorted
    by delay; the channel's fitted echoes) refitted as the best two echoes near it.

    correlation
        The channel's analytic correlation, one value a lag.
    reach_lags
        The echoes within this of the target (lags, inclusive) are its members: the pair
        replaces them all, and their model is not taken out of the data.
    model
        The template's autocorrelation (:class:`AcfModel`).
    mainlobe_lags
        The main lobe's full width at -6 dB, lags.
    threshold
        The detection threshold as a power (the threshold factor times the channel's noise
        power): the least ``a^2`` of a kept echo, and the window cost above which the other
        half-cycle basins are tried.
    search_step_lags
        The step of the complex stage's brute-force search, lags.

    The window runs from ``floor(t_first - mainlobe) - fit_half`` to ``ceil(t_last + mainlobe) +
    fit_half`` (lags, inclusive, clipped to the correlation), ``fit_half = max(1, round(mainlobe
    / 2))``, ``t_first``/``t_last`` the first and last members' delays. The data are the
    correlation there less the other echoes' model ``sum_j a_j R(s - t_j)``.

    1. Complex stage: the least-squares pair ``a_0 R(s - t_0) + a_1 R(s - t_1)`` with complex
       amplitudes, its delays searched over ``[floor(t_first - mainlobe), that + int(t_last -
       t_first + 2 mainlobe) + 2]`` at most ``floor(mainlobe)`` lags apart (the kernel's search
       domain), globally: every pair on a grid of ``search_step_lags``, then polished.
    2. Its phases read as delays: ``a = |a| exp(i phi)`` is, to the envelope's shift, ``|a|``
       at ``t - phi / rate`` (the carrier's rate, rad per lag), or ``-|a|`` half a carrier
       cycle away, whichever moves the delay less (``|phi| <= pi / 2``).
    3. The real-amplitude least-squares pair in that basin (a local fit from there).
    4. If its cost exceeds ``threshold``, the six half-cycle moves from it (each member, then
       both, half a carrier cycle earlier and later with its sign flipped) compete too, and the
       plausible fit of least cost is kept (:func:`pair_plausible`, :func:`choose`).
    5. No plausible fit: ``"merged"`` when the target stands alone and the best pair of the
       search of step 1 on whole lags lay fewer than ``ceil(mainlobe / 4)`` lags apart, else
       ``"no_pair"``.
    """
    values = np.asarray(correlation, dtype=complex)
    t_all = np.asarray(tofs, dtype=float)
    a_all = np.asarray(amplitudes, dtype=complex)
    n = len(values)
    count = len(t_all)
    first_member = last_member = target
    while first_member > 0 and t_all[target] - t_all[first_member - 1] <= reach_lags:
        first_member -= 1
    while last_member < count - 1 and t_all[last_member + 1] - t_all[target] <= reach_lags:
        last_member += 1
    members = last_member - first_member + 1
    fit_half = max(1, int(np.round(mainlobe_lags / 2)))
    start = t_all[first_member] - mainlobe_lags
    stop = t_all[last_member] + mainlobe_lags
    lo = max(math.floor(start) - fit_half, 0)
    hi = min(math.ceil(stop) + fit_half + 1, n)
    nothing = np.full(2, np.nan)
    no_pair = SplitReference(
        "no_pair", None, lo, hi, first_member, last_member,
        nothing, nothing.astype(complex), nothing, False, math.inf, None, (), False,
    )  # fmt: skip
    if hi - lo < 4:
        return no_pair
    window = model.window(lo, hi)
    others = np.r_[0:first_member, last_member + 1 : count]
    other_shapes, _ = window.shapes(t_all[others])
    data = values[lo:hi] - a_all[others] @ other_shapes

    # 1. The complex stage: brute force over pairs of delays, then a local polish.
    grid_first = float(math.floor(start))
    grid_last = grid_first + int(stop - start) + 2
    farthest = math.floor(mainlobe_lags)
    nearest = math.ceil(mainlobe_lags / 4)

    def pair_gains(step: float) -> tuple[NDArray[np.float64], NDArray[np.complex128], NDArray[np.float64]]:
        """Every pair of delays on a grid of ``step`` lags, at most ``farthest`` apart (pairs, 2),
        the amplitudes of its complex least-squares fit (pairs, 2) and the energy it removes."""
        grid = np.arange(grid_first, grid_last + step / 2, step)
        shapes, _ = window.shapes(grid)
        i, j = np.triu_indices(len(grid), 1)
        keep = grid[j] - grid[i] <= farthest + 1e-9
        i, j = i[keep], j[keep]
        basis = np.stack([shapes[i], shapes[j]], axis=-1)  # (pairs, w, 2)
        gram = np.conj(np.swapaxes(basis, 1, 2)) @ basis
        inner = np.conj(np.swapaxes(basis, 1, 2)) @ data[:, None]
        # Pairs whose shapes are (nearly) collinear fit nothing the single shape does not.
        conditioned = np.linalg.det(gram).real > 1e-9 * gram[:, 0, 0].real * gram[:, 1, 1].real
        gram = np.where(conditioned[:, None, None], gram, np.eye(2))
        fitted = np.linalg.solve(gram, inner)
        gain = np.where(conditioned, np.real(np.conj(inner) * fitted).sum(axis=(1, 2)), -np.inf)
        return np.stack([grid[i], grid[j]], axis=1), fitted[:, :, 0], gain

    pairs, _, gains = pair_gains(1.0)
    best = int(np.argmax(gains))
    if not gains[best] > 0:
        return no_pair
    grid_tofs = pairs[best]
    is_close = pairs[:, 1] - pairs[:, 0] < nearest
    close = bool(is_close[best])
    other_kind = gains[is_close != close]
    grid_gap = float((gains[best] - other_kind.max()) / gains[best]) if len(other_kind) else math.inf
    pairs, fitted, gains = pair_gains(search_step_lags)
    best = int(np.argmax(gains))

    def complex_residual(p: NDArray[np.float64]) -> NDArray[np.float64]:
        shapes, _ = window.shapes(p[:2])
        r = data - (p[2:4] + 1j * p[4:6]) @ shapes
        return np.concatenate([r.real, r.imag])

    def complex_jacobian(p: NDArray[np.float64]) -> NDArray[np.float64]:
        shapes, slopes = window.shapes(p[:2])
        a = p[2:4] + 1j * p[4:6]
        # d residual / d tau_k = -a_k d R(s - tau_k) / d tau_k; / d (Re a_k, Im a_k) = -(1, i) R.
        columns = -np.stack([a[0] * slopes[0], a[1] * slopes[1], *shapes, *(1j * shapes)])
        return np.concatenate([columns.real, columns.imag], axis=1).T

    polished = scipy.optimize.least_squares(
        complex_residual,
        np.r_[pairs[best], fitted[best].real, fitted[best].imag],
        jac=complex_jacobian,
        method="lm",
        xtol=1e-12,
        ftol=1e-14,
    ).x
    complex_tofs = polished[:2].copy()
    complex_amplitudes = polished[2:4] + 1j * polished[4:6]

    # 2. Phases read as delays, the nearer of the two signs.
    rate = model.rate_rad_per_lag
    phase = np.angle(complex_amplitudes)
    flip = np.abs(phase) > np.pi / 2
    phase = np.where(flip, phase - np.copysign(np.pi, phase), phase)
    real_tofs = complex_tofs - phase / rate
    real_amplitudes = np.where(flip, -1.0, 1.0) * np.abs(complex_amplitudes)

    # 3. The real-amplitude fit in that basin; 4. the other basins.
    def settle(t0: NDArray[np.float64], a0: NDArray[np.float64]) -> Candidate:
        def residual(p: NDArray[np.float64]) -> NDArray[np.float64]:
            shapes, _ = window.shapes(p[:2])
            r = data - p[2:] @ shapes
            return np.concatenate([r.real, r.imag])

        def jacobian(p: NDArray[np.float64]) -> NDArray[np.float64]:
            shapes, slopes = window.shapes(p[:2])
            columns = -np.stack([p[2] * slopes[0], p[3] * slopes[1], *shapes])
            return np.concatenate([columns.real, columns.imag], axis=1).T

        fit = scipy.optimize.least_squares(
            residual, np.r_[t0, a0], jac=jacobian, method="lm", xtol=1e-12, ftol=1e-14
        )
        t, a = fit.x[:2], fit.x[2:]
        cost = float(np.sum(fit.fun**2))
        spread = np.sqrt(np.maximum(cost * np.diag(np.linalg.pinv(fit.jac.T @ fit.jac)), 0.0))
        order = np.argsort(t, kind="stable")
        plausible = pair_plausible(t, a, lo, hi, mainlobe_lags, threshold)
        return Candidate(t[order], a[order], cost, plausible, spread[:2][order], spread[2:][order])

    first = settle(real_tofs, real_amplitudes)
    period = math.pi / rate  # half a carrier cycle, lags
    moves = []
    for moved in ([0], [1], [0, 1]):
        for step in (-period, period):
            t, a = first.tofs.copy(), first.amplitudes.copy()
            t[moved] += step
            a[moved] *= -1
            moves.append(settle(t, a))
    tried_moves = first.cost > threshold
    outcome, chosen = choose((first, *moves) if tried_moves else (first,), members, close)
    return SplitReference(
        outcome, chosen, lo, hi, first_member, last_member, complex_tofs, complex_amplitudes,
        grid_tofs, close, grid_gap, first, tuple(moves), tried_moves,
    )  # fmt: skip
