"""Exact reference solution of the per-row problem (eq. 13 of the TPAMI paper).

For one image row (or a block of rows sharing one ``w``, global shutter) with
``F`` of shape (N, K), column k = the row of the reference warped by pose k, and the
observed row ``g`` of shape (N,)::

    minimise    || g - F w - chi ||_2^2 + lambda_w ||w||_1 + lambda_chi ||chi||_1
    subject to  w >= 0

(METHOD.md section 2). :func:`solve_row_exact` solves it with cvxpy to tight
tolerances: it is the oracle the fast batched solver is checked against, not a
production path. :func:`row_objective` and :func:`huber_objective` evaluate the objective
in float64; for a fixed ``w`` the optimal ``chi`` is the soft-thresholded residual,
which turns the objective into a Huber loss on the residual (an exact identity).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from rsmb.ops._errors import InputError, ParameterError, SolverError

__all__ = [
    "ExactRowSolution",
    "solve_row_exact",
    "row_objective",
    "huber_objective",
    "optimal_chi",
]

# Tight tolerances for CLARABEL so that the objective is accurate to ~1e-9 relative
# (defaults are 1e-8). Passed to cvxpy's ``Problem.solve`` as solver keyword options.
_CLARABEL_OPTIONS = {
    "tol_gap_abs": 1e-10,
    "tol_gap_rel": 1e-10,
    "tol_feas": 1e-10,
    "tol_ktratio": 1e-8,
    "max_iter": 500,
}


@dataclass(frozen=True)
class ExactRowSolution:
    """Result of :func:`solve_row_exact`.

    Attributes
    ----------
    w : ndarray of float64, shape (K,)
        Pose weights, ``>= 0`` (solver round-off below 0 clipped to 0).
    chi : ndarray of float64, shape (N,)
        Signed change term, in image intensity units; 0 at excluded pixels.
    objective : float
        Objective of eq. 13 reported by the solver at the optimum.
    solve_seconds : float
        Wall time of ``Problem.solve`` alone (cvxpy compilation + solver), seconds.
    status : str
        cvxpy status, ``"optimal"``.
    solver_seconds : float
        The solver's own time as it reports it (cvxpy's
        ``solver_stats.solve_time``; NaN when it reports none): what is left
        of ``solve_seconds`` is cvxpy's compilation of the problem.
    """

    w: np.ndarray
    chi: np.ndarray
    objective: float
    solve_seconds: float
    status: str
    solver_seconds: float = float("nan")


def _check_lambda(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{name}: expected a finite number >= 0, got {value!r}") from exc
    if not (math.isfinite(v) and v >= 0):
        raise ParameterError(f"{name}: expected a finite number >= 0, got {value!r}")
    return v


def _check_problem(F, g, weights) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """float64 copies of ``F`` (N, K), ``g`` (N,) and a bool pixel mask (N,)."""
    F = np.asarray(F, dtype=np.float64)
    g = np.asarray(g, dtype=np.float64)
    if F.ndim != 2 or F.shape[0] == 0 or F.shape[1] == 0:
        raise ParameterError(f"F: expected a non-empty 2-D array (N, K), got shape {F.shape}")
    if g.shape != (F.shape[0],):
        raise ParameterError(
            f"g: expected shape ({F.shape[0]},) to match F {F.shape}, got {g.shape}"
        )
    if not np.all(np.isfinite(F)):
        raise InputError("F: holds NaN or infinite values")
    if not np.all(np.isfinite(g)):
        raise InputError("g: holds NaN or infinite values")
    if weights is None:
        keep = np.ones(F.shape[0], dtype=bool)
    else:
        wt = np.asarray(weights)
        if wt.shape != g.shape:
            raise ParameterError(f"weights: expected shape {g.shape}, got {wt.shape}")
        if not (wt.dtype == bool or np.all((wt == 0) | (wt == 1))):
            raise ParameterError("weights: expected 0/1 (or boolean) pixel weights")
        keep = wt != 0
    return F, g, keep


def _check_vector(name: str, value, n: int) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.shape != (n,):
        raise ParameterError(f"{name}: expected shape ({n},), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise InputError(f"{name}: holds NaN or infinite values")
    return v


def optimal_chi(residual, *, lambda_chi: float, weights=None) -> np.ndarray:
    """Best ``chi`` for a fixed ``w``: soft-thresholding of the residual.

    ``argmin_chi (r - chi)^2 + lambda_chi |chi|`` is
    ``chi = sign(r) max(|r| - lambda_chi / 2, 0)`` (METHOD.md section 2).

    Parameters
    ----------
    residual : ndarray, shape (N,)
        ``r = g - F w``, image intensity units.
    lambda_chi : float
        l1 weight of ``chi``, >= 0.
    weights : ndarray of {0, 1}, shape (N,), optional
        Excluded pixels (0) get ``chi = 0``.

    Returns
    -------
    ndarray of float64, shape (N,)
    """
    r = np.asarray(residual, dtype=np.float64)
    d = 0.5 * _check_lambda("lambda_chi", lambda_chi)
    chi = np.sign(r) * np.maximum(np.abs(r) - d, 0.0)
    if weights is not None:
        chi = np.where(np.asarray(weights) != 0, chi, 0.0)
    return chi


def huber_objective(F, g, w, *, lambda_w: float, lambda_chi: float, weights=None) -> float:
    """Eq. 13 with ``chi`` minimised out: ``sum_j rho(r_j) + lambda_w ||w||_1``.

    ``r = g - F w`` over the included pixels and ``rho`` is the Huber function with
    knee ``d = lambda_chi / 2``: ``rho(r) = r^2`` if ``|r| <= d`` else
    ``2 d |r| - d^2``. Equal to :func:`row_objective` with ``chi=None``.

    Parameters
    ----------
    F : ndarray, shape (N, K)
    g : ndarray, shape (N,)
    w : ndarray, shape (K,)
    lambda_w, lambda_chi : float
        Non-negative weights of ``||w||_1`` and ``||chi||_1``.
    weights : ndarray of {0, 1}, shape (N,), optional
        Pixels with weight 0 are left out of the data term.

    Returns
    -------
    float
        The objective, computed in float64.
    """
    F, g, keep = _check_problem(F, g, weights)
    w = _check_vector("w", w, F.shape[1])
    lw = _check_lambda("lambda_w", lambda_w)
    d = 0.5 * _check_lambda("lambda_chi", lambda_chi)
    return _huber_loss((g - F @ w)[keep], d) + lw * float(np.abs(w).sum())


def _huber_loss(residual, delta):
    """``sum_j rho(r_j)``: the Huber function with knee ``delta`` (eq. 13's data
    and change terms with ``chi`` minimised out), summed in float64."""
    a = np.abs(np.asarray(residual, np.float64))
    return float(np.where(a <= delta, a * a, 2.0 * delta * a - delta * delta).sum())


def row_objective(
    F, g, w, chi=None, *, lambda_w: float, lambda_chi: float, weights=None
) -> float:
    """Objective of eq. 13, ``||m (g - F w - chi)||^2 + lambda_w ||w||_1 + lambda_chi ||chi||_1``.

    Parameters
    ----------
    F : ndarray, shape (N, K)
        Warped reference row(s), column k for pose k; intensity units.
    g : ndarray, shape (N,)
        Observed row(s), intensity units.
    w : ndarray, shape (K,)
        Pose weights (not checked for sign; ``||w||_1`` uses ``|w|``).
    chi : ndarray, shape (N,), optional
        Signed change term. Default: the optimal one for this ``w``
        (:func:`optimal_chi`), which makes this equal to :func:`huber_objective`.
    lambda_w, lambda_chi : float
        Non-negative weights of ``||w||_1`` and ``||chi||_1``.
    weights : ndarray of {0, 1}, shape (N,), optional
        Mask ``m``: pixels with weight 0 are left out of the data term.

    Returns
    -------
    float
        The objective, computed in float64.
    """
    F, g, keep = _check_problem(F, g, weights)
    w = _check_vector("w", w, F.shape[1])
    lw = _check_lambda("lambda_w", lambda_w)
    lc = _check_lambda("lambda_chi", lambda_chi)
    r = g - F @ w
    if chi is None:
        chi = optimal_chi(r, lambda_chi=lc, weights=keep)
    else:
        chi = _check_vector("chi", chi, F.shape[0])
    e = (r - chi)[keep]
    return float(e @ e + lw * np.abs(w).sum() + lc * np.abs(chi).sum())


def _build_problem(F: np.ndarray, g: np.ndarray, keep: np.ndarray, lw: float, lc: float):
    """cvxpy problem of eq. 13 over the included pixels.

    The residual is its own variable ``e`` tied by an equality constraint, so that the
    quadratic term handed to the solver is the identity (sparse, well conditioned)
    rather than the dense ``[F I]^T [F I]``.
    """
    import cvxpy as cp

    Fk, gk = F[keep], g[keep]
    n, k = Fk.shape
    w = cp.Variable(k, name="w", nonneg=True)
    chi = cp.Variable(n, name="chi")
    e = cp.Variable(n, name="residual")
    objective = cp.sum_squares(e) + lw * cp.sum(w) + lc * cp.norm1(chi)
    constraints = [e == gk - Fk @ w - chi]
    return cp.Problem(cp.Minimize(objective), constraints), w, chi


def solve_row_exact(
    F,
    g,
    *,
    lambda_w: float,
    lambda_chi: float,
    solver: str = "CLARABEL",
    weights=None,
    solver_options: dict | None = None,
) -> ExactRowSolution:
    """Solve the per-row problem of eq. 13 exactly with cvxpy (the reference oracle).

    ``minimise ||g - F w - chi||^2 + lambda_w ||w||_1 + lambda_chi ||chi||_1, w >= 0``.

    Parameters
    ----------
    F : ndarray, shape (N, K)
        Column k = row of the reference warped (and, for a block of rows sharing one
        ``w``, e.g. global shutter, rows stacked: ``N = rows * width``) by pose k;
        image intensities, typically float32 in [0, 1].
    g : ndarray, shape (N,)
        Observed row(s), same units.
    lambda_w : float
        Weight of ``||w||_1`` (>= 0); since ``w >= 0`` this is ``lambda_w * sum(w)``.
    lambda_chi : float
        Weight of ``||chi||_1`` (>= 0), in the same (intensity) scaling: residuals
        beyond ``lambda_chi / 2`` go to ``chi``.
    solver : str, optional
        cvxpy solver name, default ``"CLARABEL"``.
    weights : ndarray of {0, 1}, shape (N,), optional
        Pixel weights: 0 leaves the pixel out of the data term (nodata, outside the
        warp); its ``chi`` is 0.
    solver_options : dict, optional
        Keyword options for ``Problem.solve``. Default for CLARABEL: gap and
        feasibility tolerances of 1e-10 (objective accurate to ~1e-9 relative);
        none for other solvers.

    Returns
    -------
    ExactRowSolution
        ``w`` (K,), ``chi`` (N,), the objective, the time of ``Problem.solve`` and the
        status.

    Raises
    ------
    ParameterError
        Bad shapes, negative or non-finite lambdas, non-0/1 weights, or a solver that
        does not reach status ``"optimal"`` (the message gives the status).
    InputError
        NaN or infinite values in ``F`` or ``g``.
    """
    import cvxpy as cp

    F, g, keep = _check_problem(F, g, weights)
    lw = _check_lambda("lambda_w", lambda_w)
    lc = _check_lambda("lambda_chi", lambda_chi)
    if solver_options is None:
        solver_options = dict(_CLARABEL_OPTIONS) if solver.upper() == "CLARABEL" else {}
    if not np.any(keep):
        # no pixel in the data term: the l1 penalty alone gives w = 0, chi = 0
        k = F.shape[1]
        return ExactRowSolution(
            w=np.zeros(k), chi=np.zeros(F.shape[0]), objective=0.0,
            solve_seconds=0.0, status=cp.OPTIMAL, solver_seconds=0.0,
        )
    problem, w_var, chi_var = _build_problem(F, g, keep, lw, lc)
    t0 = time.perf_counter()
    try:
        problem.solve(solver=solver, **solver_options)
    except cp.error.SolverError as exc:
        raise SolverError(f"solver: {solver!r} failed on this problem: {exc}") from exc
    seconds = time.perf_counter() - t0
    if problem.status != cp.OPTIMAL:
        raise SolverError(
            f"solver: expected status 'optimal' from {solver!r}, got {problem.status!r} "
            f"(F {F.shape}, lambda_w={lw}, lambda_chi={lc})"
        )
    w = np.maximum(np.asarray(w_var.value, dtype=np.float64), 0.0)
    chi = np.zeros(F.shape[0], dtype=np.float64)
    chi[keep] = np.asarray(chi_var.value, dtype=np.float64)
    return ExactRowSolution(
        w=w, chi=chi, objective=float(problem.value), solve_seconds=seconds,
        status=str(problem.status), solver_seconds=_solver_time(problem),
    )


def _solver_time(problem):
    stats = problem.solver_stats
    seconds = None if stats is None else stats.solve_time
    return float("nan") if seconds is None else float(seconds)
