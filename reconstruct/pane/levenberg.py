"""Bounded Levenberg-Marquardt on residuals in noise units, with the covariance at the optimum, and the protocol of
the pane model that calibrate-pane's fit differentiates.

The fit (:mod:`reconstruct.pane.calibrate` and its stages) needs phi_perp, theta and the Fresnel maps of a pane
hypothesis x = (tilt, azimuth, fov, n) with their Jacobian.  It takes them from a :class:`PaneModelFactory`, given
by its caller: ``polspike calibrate-pane`` passes the differentiable maps tier
(:class:`generator.pane_fit.PaneModelAD`, Dr.Jit forward AD), which this package may not import (it runs on real
captures without the renderer).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Protocol

import numpy as np


class PaneModel(Protocol):
    """The maps of a pane hypothesis x = (tilt, azimuth, fov, n) (radians; n the index) on a pixel or block grid."""

    def maps(self, x) -> dict[str, np.ndarray]:
        """theta, phi_perp, R_perp, R_par, T_perp, T_par, each (h, w), for hypothesis x."""

    def maps_and_jacobian(self, x, wrt: tuple[int, ...] = (0, 1, 2, 3)) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """:meth:`maps` and their derivatives along the parameters ``wrt`` (each (len(wrt), h, w))."""


class PaneModelFactory(Protocol):
    """Builds a :class:`PaneModel` for a width x height view, a pane model (single / thin_slab / thick_slab) and a grid:
    ``sub`` rays per pixel side, or one ray per ``block`` x ``block`` pixels.
    """

    def __call__(self, width: int, height: int, model: str = "single", *, sub: int = 1, block: int = 0) -> PaneModel: ...



@dataclasses.dataclass
class FitResult:
    """Outcome of :func:`gauss_newton`: x, covariance (GN Hessian inverse x reduced chi^2 when > 1), chi2, dof, history."""

    x: np.ndarray
    cov: np.ndarray
    chi2: float
    dof: int
    history: list[dict]
    hessian: np.ndarray
    converged: bool

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.cov), 0.0))


def gauss_newton(
    fun: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    x0,
    lb,
    ub,
    *,
    max_iter: int = 30,
    tol: float = 1e-7,
    lam0: float = 1e-3,
) -> FitResult:
    """Bounded Levenberg-Marquardt on residuals r(x) in noise units (fun returns (r (m,), J (m, k))).

    The covariance is (J^T J)^-1 at the optimum, scaled by the reduced chi^2 when it exceeds 1
    (model misfit or underestimated noise widen the error bars, never narrow them).
    """
    x = np.asarray(x0, np.float64).copy()
    lb, ub = np.asarray(lb, np.float64), np.asarray(ub, np.float64)
    x = np.clip(x, lb, ub)
    r, J = fun(x)
    cost = float(r @ r)
    lam = lam0
    hist = [{"iter": 0, "chi2": cost, "x": x.tolist(), "lambda": lam}]
    converged = False
    for it in range(1, max_iter + 1):
        A = J.T @ J
        g = J.T @ r
        D = np.diag(np.maximum(np.diag(A), 1e-12))
        improved = False
        for _ in range(12):
            try:
                step = -np.linalg.solve(A + lam * D, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            xn = np.clip(x + step, lb, ub)
            rn, Jn = fun(xn)
            cn = float(rn @ rn)
            if np.isfinite(cn) and cn <= cost:
                improved = True
                done = (cost - cn) <= tol * max(cost, 1e-30) and float(np.max(np.abs(xn - x))) < 1e-7 + 1e-6 * float(np.max(np.abs(x)))
                x, r, J, cost = xn, rn, Jn, cn
                lam = max(lam / 5, 1e-9)
                break
            lam *= 10
        hist.append({"iter": it, "chi2": cost, "x": x.tolist(), "lambda": lam})
        if not improved or done:
            converged = True
            break
    A = J.T @ J
    dof = max(1, r.size - x.size)
    try:
        cov = np.linalg.pinv(A)
    except np.linalg.LinAlgError:  # pragma: no cover
        cov = np.full((x.size, x.size), np.inf)
    red = cost / dof
    cov = cov * max(1.0, red)
    return FitResult(x, cov, cost, dof, hist, A, converged)
