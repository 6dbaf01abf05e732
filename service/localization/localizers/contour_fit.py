"""Array maths shared by the object localizers: how well object poses fit the readings.

The counterpart of `fitting.py` and `refine.py` for a held object: a reading is a fingertip
centre (x, z) with its tip's radius, and its residual under a pose is the centre's signed
distance from the object minus the radius (`objects/kernels.py`). There is no unknown
offset: the hand measures centres in its own frame, and so does the pose.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.linalg import solve_triangular

from service.localization.localizers.base import wrap_angle
from service.localization.localizers.fitting import log_likelihood
from service.localization.localizers.refine import (
    Fit,
    _covariance,
    _sd,
    sandwich,
    shared_error,
)
from service.localization.objects import kernels
from service.localization.objects.field import ContactField


def _rows(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


def residuals(field: ContactField, poses: np.ndarray, points: np.ndarray, radii: np.ndarray
              ) -> np.ndarray:
    """(N, K) residuals of readings `points` (K, 2) with tip radii (K,) under poses (N, 3)."""
    return kernels.residuals(*field.args, _rows(poses), _rows(points), _rows(radii))


def fit_log_likelihood(field: ContactField, poses: np.ndarray, points: np.ndarray,
                       radii: np.ndarray, sd: float | np.ndarray, outlier_probability: float,
                       outlier_range: float) -> np.ndarray:
    """Log likelihood (N,) of each pose on every reading at sd `sd`."""
    r = residuals(field, poses, points, radii)
    ll = log_likelihood(r, np.ones(r.shape, dtype=bool), sd, outlier_probability,
                        outlier_range)
    return np.where(np.isfinite(ll), ll, -np.inf)


def gauss_newton(field: ContactField, poses: np.ndarray, points: np.ndarray, radii: np.ndarray,
                 weights: np.ndarray | None = None, iterations: int = 3, damping: float = 1e-4,
                 max_move: float | None = None) -> np.ndarray:
    """A few damped Gauss-Newton steps for every pose at once; steps capped at `max_move`
    metres (and max_move / lever radians) so a pose never jumps to another basin."""
    weights = np.ones(len(points)) if weights is None else weights
    lever = max(field.contour.max_radius + 0.01, max_move or 0.0)  # centroid to a tip centre
    return kernels.gauss_newton(*field.args, _rows(poses), _rows(points), _rows(radii),
                                _rows(weights), iterations, damping, max_move or 0.0, lever)


def whitened_fit(field: ContactField, pose: np.ndarray, points: np.ndarray,
                 radii: np.ndarray, chol: np.ndarray, iterations: int, max_move: float
                 ) -> tuple[np.ndarray, float]:
    """Damped Gauss-Newton from `pose` with the readings' errors correlated, of covariance
    `chol` @ `chol`.T (`chol` its lower Cholesky factor): residuals and Jacobian whitened
    by it (generalized least squares). Steps are capped as `gauss_newton`'s (`max_move`
    metres, and max_move / lever radians; none at or below zero). Returns the best pose
    met and its chi-square."""
    lever = max(field.contour.max_radius + 0.01, max_move)
    pose = np.asarray(pose, dtype=np.float64).copy()
    best, best_chi2 = pose.copy(), np.inf
    for i in range(iterations + 1):
        r, j = _model(field, points, radii, pose)
        white = solve_triangular(chol, np.column_stack([r, j]), lower=True)
        r, j = white[:, 0], white[:, 1:]
        chi2 = float(r @ r)
        if chi2 < best_chi2:
            best, best_chi2 = pose.copy(), chi2
        if i == iterations:
            break
        normal = j.T @ j
        normal += 1e-6 * np.diag(np.diag(normal))
        try:
            step = -np.linalg.solve(normal, j.T @ r)
        except np.linalg.LinAlgError:
            break
        if max_move > 0:
            step /= max(np.hypot(step[0], step[1]) / max_move,
                        abs(step[2]) * lever / max_move, 1.0)
        pose += step
    best[2] = wrap_angle(best[2])
    return best, best_chi2


def _model(field: ContactField, points: np.ndarray, radii: np.ndarray, pose: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray]:
    return kernels.residuals_and_jacobian(*field.args, _rows(pose), _rows(points),
                                          _rows(radii))


def _fit_at(field: ContactField, points: np.ndarray, radii: np.ndarray, pose: np.ndarray,
            sigma: np.ndarray) -> Fit:
    r, j = _model(field, points, radii, pose)
    r, j = r / sigma, j / sigma[:, np.newaxis]
    cov = _covariance(j)
    return Fit(pose=(float(pose[0]), float(pose[1]), float(wrap_angle(pose[2]))),
               position_sd=float(np.sqrt(max(cov[0, 0] + cov[1, 1], 0.0))),
               heading_sd=float(np.sqrt(max(cov[2, 2], 0.0))),
               rms=float(np.sqrt(np.mean(r**2))), max_abs=float(np.max(np.abs(r))),
               readings=len(points))


def correlated_spread(field: ContactField, points: np.ndarray, radii: np.ndarray,
                      pose: np.ndarray, sd: np.ndarray, error_sd: float, length: float
                      ) -> tuple[float, float]:
    """Position and heading sd of the least-squares pose (readings weighed by their `sd`)
    when the world's outline also differs from the model's by a smooth error of sd
    `error_sd` that readings `length` apart share (a Gaussian correlation): the sandwich
    A^-1 J^T W S W J A^-1 of `refine.correlated_spread`, for a contour. (keyed:124, seed
    124, three fingers: declared 3.6 degrees off at a spread of 0.75 degrees, where this
    says 1.3.)"""
    _, j = _model(field, points, radii, np.asarray(pose, dtype=np.float64))
    cov = sandwich(j, sd, shared_error(points, error_sd, length))
    return _sd(cov[0, 0] + cov[1, 1]), _sd(cov[2, 2])


def assess(field: ContactField, points: np.ndarray, radii: np.ndarray, pose: np.ndarray,
           sigma: float | np.ndarray) -> Fit:
    """How well `pose` explains the readings, without moving it, and its covariance."""
    sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (len(points),))
    return _fit_at(field, points, radii, np.asarray(pose, dtype=np.float64), sigma)


def refine(field: ContactField, points: np.ndarray, radii: np.ndarray, start: np.ndarray,
           sigma: float | np.ndarray, iterations: int = 12, outlier_gate: float = 6.0,
           max_outliers: int = 2) -> Fit:
    """Least-squares pose from `start` (damped Gauss-Newton); then, like `refine.refine`,
    the worst reading beyond `outlier_gate` sigmas is set aside and the fit repeated, at
    most `max_outliers` times and never below six readings."""
    sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (len(points),))
    pose = np.asarray(start, dtype=np.float64)
    use = np.ones(len(points), dtype=bool)
    for _ in range(1 + max_outliers):
        if use.sum() >= 3:
            pose = _solve(field, points[use], radii[use], sigma[use], pose, iterations)
        r = np.where(use, np.abs(_model(field, points, radii, pose)[0] / sigma), 0.0)
        worst = int(np.argmax(r))
        if r[worst] <= outlier_gate or use.sum() - 1 < 6 or (~use).sum() >= max_outliers:
            break
        use[worst] = False
    fit = _fit_at(field, points[use], radii[use], pose, sigma[use])
    return fit if use.all() else dataclasses.replace(fit, kept=np.flatnonzero(use))


def _solve(field: ContactField, points: np.ndarray, radii: np.ndarray, sigma: np.ndarray,
           pose: np.ndarray, iterations: int) -> np.ndarray:
    """Damped Gauss-Newton to convergence (the compiled kernel): from a polished start a
    handful of iterations settle, at a fraction of a scipy solver's overhead."""
    return gauss_newton(field, pose[None], points, radii, 1.0 / sigma**2,
                        iterations=iterations, damping=1e-6)[0]


def distinct_places(points: np.ndarray, cell: float) -> int:
    """How many `cell`-sized squares the readings (K, 2) fall in."""
    ix, iz = np.round(points / cell).astype(np.int64).T
    return len(np.unique(ix * (1 << 32) + iz))


def poses_through(field: ContactField, point: np.ndarray, radius: float,
                  heading_step: float, arc_step: float) -> np.ndarray:
    """Every pose (N, 3) under which a fingertip of `radius` centred at `point` (2,) touches
    the object: headings every `heading_step`, and for each the outline points under the
    fingertip every `arc_step` of arc."""
    outline, normals = field.contour.resampled(arc_step)
    local = outline + radius * normals  # the centre, object frame
    headings = np.arange(-np.pi, np.pi, heading_step)
    c, s = np.cos(headings)[:, None], np.sin(headings)[:, None]
    x = point[0] - (c * local[None, :, 0] - s * local[None, :, 1])
    z = point[1] - (s * local[None, :, 0] + c * local[None, :, 1])
    heading = np.broadcast_to(headings[:, None], x.shape)
    return np.column_stack([x.ravel(), z.ravel(), heading.ravel()])
