"""Continuous refinement: fit (x, y, heading) to every reading by nonlinear least squares.

Discrete and sampled hypotheses are only as good as their spacing; once they concentrate,
fitting the start pose to the whole history (damped Gauss-Newton, compiled) gives a
continuous estimate and, from the Jacobian, its uncertainty. The unknown height offset
between hand and map is fitted too, so the first contact is one noisy reading among others
rather than an exact reference.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.distance import cdist

from service.localization.localizers.base import wrap_angle
from service.localization.localizers.fitting import (
    gauss_newton,
    heights_and_jacobian,
    sample,
    slope_squares,
)
from service.localization.surface import ContactSurface


@dataclass(frozen=True)
class Fit:
    """A refined start pose and how well it explains the readings."""

    pose: tuple[float, float, float]
    position_sd: float
    """Metres: 1-sigma position uncertainty from the fit's covariance."""
    heading_sd: float
    """Radians."""
    rms: float
    """Root-mean-square residual in units of the sensor sigma (about 1 for the truth)."""
    max_abs: float
    """Largest residual, in units of the sensor sigma."""
    readings: int
    """Readings the fit kept (those beyond the outlier gate are left out)."""
    information: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)), repr=False,
                                    compare=False)
    """(3, 3) what the readings tell about (x0, y0, heading), the height offset
    marginalized: zero along a direction they do not see (the covariance is its inverse)."""
    kept: np.ndarray | None = field(default=None, repr=False, compare=False)
    """Indexes of the readings the fit kept (`refine` sets outliers aside); None: all."""
    max_abs_shared: float = float("nan")
    """Largest residual over all the error a reading is expected to have: its own sd and
    the map's error that nearby readings share (`convergence._with_model_error`); nan
    where that error is not modelled (without noise)."""


def reading_sigmas(surface: ContactSurface, history: np.ndarray, pose: np.ndarray,
                   sigma: float, position_sigma: float) -> np.ndarray:
    """Residual sd of each reading at `pose`: the height noise, plus the measured position's
    noise (in this reading and the first) turned into height by the local slope, so steep
    readings weigh less and the covariance is honest."""
    _, jac = heights_and_jacobian(surface, np.asarray(pose, dtype=np.float64), history)
    return _slope_sigmas(jac, sigma, position_sigma)


def reading_sigmas_at(surface: ContactSurface, history: np.ndarray, pose: np.ndarray,
                      sigmas: tuple[float, ...], position_sigma: float
                      ) -> list[np.ndarray]:
    """`reading_sigmas` at `pose` for each height sd of `sigmas`, the slopes read once."""
    _, jac = heights_and_jacobian(surface, np.asarray(pose, dtype=np.float64), history)
    return [_slope_sigmas(jac, sigma, position_sigma) for sigma in sigmas]


def reading_sigmas_each(surface: ContactSurface, history: np.ndarray, poses: np.ndarray,
                        sigma: float, position_sigma: float) -> np.ndarray:
    """`reading_sigmas` for every pose of `poses` (N, 3) at once: (N, K)."""
    return _widened(slope_squares(surface, poses, history), sigma, position_sigma)


def _slope_sigmas(jac: np.ndarray, sigma: float, position_sigma: float) -> np.ndarray:
    """`reading_sigmas` from the readings' Jacobian (K, 3) at the pose."""
    return _widened(jac[:, 0]**2 + jac[:, 1]**2, sigma, position_sigma)


def _widened(slope_squared: np.ndarray, sigma: float, position_sigma: float) -> np.ndarray:
    """The height sd `sigma` widened by the position noise of a reading and of the first
    contact, turned into height by the squared slope under the reading."""
    return np.sqrt(sigma**2 + 2 * position_sigma**2 * slope_squared)


def _model(surface: ContactSurface, history: np.ndarray, params: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray]:
    """Residuals of (x0, y0, heading, offset) and their Jacobian by the free parameters:
    all four, or on a profile x0 and the offset (y0 and the direction are fixed there)."""
    z, jac = heights_and_jacobian(surface, params[:3], history)
    return z - params[3] - history[:, 2], _design(surface, jac)


def _design(surface: ContactSurface, jac: np.ndarray) -> np.ndarray:
    """The Jacobian by the free parameters (`_free`) from the heights' Jacobian (K, 3) by
    the pose: the offset's column is -1."""
    return np.column_stack([jac, -np.ones(len(jac))])[:, _free(surface)]


def _over_all(surface: ContactSurface, block: np.ndarray) -> np.ndarray:
    """A matrix over the free parameters as one over all four, zero where a profile fits
    none (its y0 and heading)."""
    if not surface.map.is_profile:
        return block
    full = np.zeros((4, 4))
    full[np.ix_(_free(surface), _free(surface))] = block
    return full


def _free(surface: ContactSurface) -> list[int]:
    """Indexes of the fitted parameters among (x0, y0, heading, offset)."""
    return [0, 3] if surface.map.is_profile else [0, 1, 2, 3]


def refine(surface: ContactSurface, history: np.ndarray, start: np.ndarray,
           sigma: float | np.ndarray, iterations: int = 20, outlier_gate: float = 6.0,
           max_outliers: int = 2) -> Fit:
    """Least-squares start pose from `start` (3,) for readings `history` (K, 3), K >= 4.

    `sigma` is the residual sd of a reading (metres; one, or one per reading); it weights
    the fit and turns the Jacobian into a covariance. Damped Gauss-Newton converges from a
    few millimetres and degrees off in a handful of iterations (a robust loss there
    crawls); then the worst reading, if beyond `outlier_gate` sigmas (a slip, a bump the
    map lacks), is dropped and the fit repeated, up to `max_outliers` times. (It was
    scipy's least_squares: the same fits, several times the cost in Python callbacks.)

    The gate is 6 sigmas, not 4: the truth's worst residual on B2 stays under 2.5, and at
    4 a wrong pose 89 cm off (80-unit map, seed 7, `work=4000`) shed its one 4.8-sigma
    reading, fitted the rest at 1.05 sigma RMS and was declared. At 6 no B2 reading is
    dropped and B2's results are unchanged.
    """
    start = np.asarray(start, dtype=np.float64)
    z0 = float(sample(surface, start[0], start[1])[0])
    params = np.array([start[0], start[1], start[2], z0 - history[0, 2]])
    sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (len(history),))
    use = np.ones(len(history), dtype=bool)
    for _ in range(1 + max_outliers):
        params = _solve(surface, history[use], params, sigma[use], iterations)
        r = np.where(use, np.abs(_model(surface, history, params)[0] / sigma), 0.0)
        worst = int(np.argmax(r))
        if r[worst] <= outlier_gate or use.sum() - 1 < 6 or (~use).sum() >= max_outliers:
            break
        use[worst] = False  # the worst reading only: one slip distorts the fit everywhere
    fit = _fit_at(surface, history[use], params, sigma[use])
    return fit if use.all() else dataclasses.replace(fit, kept=np.flatnonzero(use))


def assess(surface: ContactSurface, history: np.ndarray, pose: np.ndarray,
           sigma: float | np.ndarray) -> Fit:
    """How well `pose` (3,) explains the readings, without moving it: the residuals with
    the height offset fitted, and the covariance the Jacobian implies. Cheap (no solver),
    for steps where no declaration is in reach."""
    pose = np.asarray(pose, dtype=np.float64)
    z, _ = heights_and_jacobian(surface, pose, history)
    params = np.array([pose[0], pose[1], pose[2], float(np.mean(z - history[:, 2]))])
    sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (len(history),))
    return _fit_at(surface, history, params, sigma)


def _fit_at(surface: ContactSurface, history: np.ndarray, params: np.ndarray,
            sigma: np.ndarray) -> Fit:
    """The `Fit` of the parameters (x0, y0, heading, offset) on these readings: residuals
    in sigmas, and the covariance their Jacobian implies."""
    r, j = _model(surface, history, params)
    r, j = r / sigma, j / sigma[:, np.newaxis]
    seen = j.T @ j
    cov, normal = _over_all(surface, _inverse(seen)), _over_all(surface, seen)
    offset = normal[3, 3] if normal[3, 3] > 0 else np.inf
    information = normal[:3, :3] - np.outer(normal[:3, 3], normal[3, :3]) / offset
    return Fit(pose=(float(params[0]), float(params[1]), float(wrap_angle(params[2]))),
               position_sd=_sd(cov[0, 0] + cov[1, 1]), heading_sd=_sd(cov[2, 2]),
               rms=float(np.sqrt(np.mean(r**2))), max_abs=float(np.max(np.abs(r))),
               readings=len(history), information=information)


def correlated_spread(surface: ContactSurface, history: np.ndarray, pose: np.ndarray,
                      sigma: float, position_sigma: float, error_sd: float, length: float
                      ) -> tuple[float, float]:
    """Position and heading sd of the least-squares pose (`refine`, each reading weighed
    by its `reading_sigmas`) when the map also differs from the object by a smooth error of
    sd `error_sd` that readings `length` apart share (a Gaussian correlation): the fit's
    own covariance assumes every reading errs alone, and on a gently curved shell a shared
    error of 0.2 mm moves the fit by millimetres (shell:20:5, seed 2: declared 4.2 mm off
    with a claimed sd of 0.6 mm). The estimator is unchanged; its covariance is the
    sandwich A^-1 J^T W S W J A^-1, S the readings' covariance, A = J^T W J."""
    _, jac = heights_and_jacobian(surface, np.asarray(pose, dtype=np.float64), history)
    cov = _over_all(surface, sandwich(_design(surface, jac),
                                      _slope_sigmas(jac, sigma, position_sigma),
                                      shared_error(history, error_sd, length)))
    return _sd(cov[0, 0] + cov[1, 1]), _sd(cov[2, 2])


def sandwich(j: np.ndarray, sd: np.ndarray, shared: np.ndarray) -> np.ndarray:
    """Covariance A^-1 J^T W (diag(sd^2) + shared) W J A^-1 of the least-squares estimate
    with design `j` (K, P), readings weighed by their own `sd` (K,), when they also share
    the error of covariance `shared` (K, K); A = J^T W J, W = diag(sd^-2). Unbounded where
    A is (`_inverse`)."""
    weighed = j / np.asarray(sd)[:, np.newaxis] ** 2  # W J
    normal = j.T @ weighed  # A
    inner = normal + weighed.T @ shared @ weighed
    bread = _inverse(normal)
    return bread @ inner @ bread if np.all(np.isfinite(bread)) else bread


def worst_over_whole_error(surface: ContactSurface, history: np.ndarray, pose: np.ndarray,
                           sigma: float, position_sigma: float) -> float:
    """The largest residual at `pose` (the height offset fitted), each reading's over its
    whole expected error: its own sd (`reading_sigmas`) and the map's error `sigma` that
    nearby readings share (`Fit.max_abs_shared`). One pass over the readings."""
    z, jac = heights_and_jacobian(surface, np.asarray(pose, dtype=np.float64), history)
    whole = np.hypot(_slope_sigmas(jac, sigma, position_sigma), sigma)
    r = z - np.mean(z - history[:, 2]) - history[:, 2]
    return float(np.max(np.abs(r / whole)))


def shared_error(history: np.ndarray, error_sd: float, length: float) -> np.ndarray:
    """(K, K) covariance of the error the readings share where the map differs from the
    object smoothly: sd `error_sd`, a Gaussian correlation over `length` (as far apart as
    readings a step apart, about 0.6)."""
    xy = history[:, :2]
    return error_sd**2 * np.exp(-0.5 / length**2 * cdist(xy, xy, "sqeuclidean"))


def _sd(variance: float) -> float:
    """The sd of a variance; a variance that is not finite, or below zero (round-off), leaves
    the spread unbounded, never quietly the narrower one it would replace."""
    return float(np.sqrt(variance)) if np.isfinite(variance) and variance >= 0 else float("inf")


def _covariance(jac: np.ndarray) -> np.ndarray:
    """(J^T J)^-1 of a Jacobian scaled by the readings' sd (`_inverse`)."""
    return _inverse(jac.T @ jac)


NEARLY_SINGULAR = 1e-9
"""Smallest eigenvalue, relative to the diagonal (`_inverse`), of normal equations whose
inverse is a covariance rather than round-off."""


def _inverse(normal: np.ndarray) -> np.ndarray:
    """The covariance of normal equations J^T J. A direction the readings do not see at
    all (along a straight rib, across a flat patch) has unbounded variance: the inverse
    raises there, and the answer is infinity, never the pseudo-inverse's zero, which once
    declared a plate pose 23 mm off along a rib (plate:20:1, seed 0). So does a direction
    they see next to nothing of: the inverse of such equations is round-off, and on a plain
    with two small holes it gave a spread of 0.0 mm at one step and 640 m at the one before
    (a helper's held-out surface), so the equations scaled to a unit diagonal must keep
    their smallest eigenvalue above `NEARLY_SINGULAR`."""
    scale = np.sqrt(np.diag(normal))
    if not (np.all(np.isfinite(normal)) and np.all(scale > 0)):
        return np.full(normal.shape, np.inf)
    unit = normal / np.outer(scale, scale)
    if np.linalg.eigvalsh(unit)[0] <= NEARLY_SINGULAR:
        return np.full(normal.shape, np.inf)
    cov = np.linalg.inv(unit) / np.outer(scale, scale)
    return cov if np.all(np.isfinite(cov)) else np.full(normal.shape, np.inf)


def _solve(surface: ContactSurface, history: np.ndarray, params: np.ndarray, sigma: np.ndarray,
           iterations: int) -> np.ndarray:
    """Weighted Gauss-Newton to convergence (`fitting.gauss_newton`, compiled: the height
    offset eliminated, lightly damped, so it behaves as Levenberg-Marquardt near a fit),
    then the offset that goes with the pose."""
    if len(history) < len(_free(surface)):  # under-determined: nothing to fit yet
        return params
    pose = gauss_newton(surface, params[np.newaxis, :3], history, 1.0 / sigma**2,
                        iterations=iterations, damping=1e-6)[0]
    z, _ = heights_and_jacobian(surface, pose, history)
    w = 1.0 / sigma**2
    return np.append(pose, float(np.sum(w * (z - history[:, 2])) / np.sum(w)))
