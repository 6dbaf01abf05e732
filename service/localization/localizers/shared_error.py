"""What the world's shared error makes of a held object's readings: the world's outline
differs from the model's coherently (B2's mismatch: sd `mismatch_sd` along the normals,
over `mismatch_length` along the outline), so readings in one patch err together, and all
of them may lie off the model alike. The object judge (`object_judge.py`) weighs its tracks
and widens its declared spread by these."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.linalg import cholesky

from service.localization.localizers.contour_fit import (
    correlated_spread,
    distinct_places,
    refine,
    residuals,
    whitened_fit,
)
from service.localization.localizers.fitting import log_likelihood
from service.localization.localizers.object_base import ObjectContext
from service.localization.localizers.refine import Fit, shared_error

FIT_ITERATIONS = 10
"""Gauss-Newton steps that fit each pose `correlated_fits` weighs, as many as the images'
polish takes (`object_judge._images`)."""


def offset_log_likelihood(ctx: ObjectContext, poses: np.ndarray, points: np.ndarray,
                           radii: np.ndarray, sd: float, temper: float) -> np.ndarray:
    """Tempered log likelihood (N,) of each pose on the readings, the world's outline
    allowed to lie off the model's by one offset along its normals everywhere (fitted per
    pose, with a prior of sd `ctx.sigma`). A world a fraction of a millimetre larger or
    smaller - a part's tolerance, a tip's radius - leaves every reading off the truth alike,
    and so does a world whose mismatch happens to lie outward under every fingertip: a pose
    far off can fit such readings better than the truth (rounded:8, seed 8, three fingers:
    every reading 0.0-0.9 mm outside the truth, 0.25-0.75 mm on average per finger's arc;
    a pose 125 degrees off was declared at 0.9994). No offset when the model is exact."""
    return offset_log_likelihood_of(ctx, residuals(ctx.field, poses, points, radii), sd,
                                    temper)


def offset_log_likelihood_of(ctx: ObjectContext, r: np.ndarray, sd: float | np.ndarray,
                             temper: float) -> np.ndarray:
    """`offset_log_likelihood` from the residuals (N, K) already computed, positive outside:
    what a pool that keeps its members' residuals weighs them by."""
    offset = (shared_offset(ctx, r, sd) if ctx.mismatch_length > 0
              else np.zeros(len(r)))
    ll = log_likelihood(r - offset[:, None], np.ones(r.shape, dtype=bool), sd,
                        ctx.outlier_probability, ctx.outlier_range)
    ll = temper * np.where(np.isfinite(ll), ll, -np.inf)
    return ll - 0.5 * (offset / ctx.sigma) ** 2


def shared_offset(ctx: ObjectContext, r: np.ndarray, sd: float | np.ndarray) -> np.ndarray:
    """The offset (N,) the residuals (N, K) of each pose share: their weighted mean, shrunk
    towards zero by a prior of sd `ctx.sigma`."""
    w = np.broadcast_to(1.0 / np.asarray(sd, dtype=np.float64) ** 2, r.shape[1:])
    return (r * w).sum(axis=1) / (w.sum() + 1.0 / ctx.sigma**2)


def correlation_length(mismatch_length: float) -> float:
    """The length of the Gaussian correlation of the world's mismatch between readings:
    it is white noise smoothed by a Gaussian of sd `mismatch_length` along the outline, so
    readings d apart share exp(-d^2 / 4 L^2) of it, a correlation of length sqrt(2) L."""
    return float(np.sqrt(2.0) * mismatch_length)


def correlated_fits(ctx: ObjectContext, poses: np.ndarray, points: np.ndarray,
                    radii: np.ndarray, sd: float | np.ndarray,
                    iterations: int = FIT_ITERATIONS) -> tuple[np.ndarray, np.ndarray]:
    """Each of `poses` fitted to the readings (`iterations` Gauss-Newton steps,
    `contour_fit.whitened_fit`) with their errors weighed as the world makes them, and its
    chi-square: each reading's own sd `sd`, the mismatch readings share
    (`correlation_length`), and the one offset all of them share (prior sd `ctx.sigma`, as
    `offset_log_likelihood`) - generalized least squares. The covariance is positive
    definite, as every sd is above zero with noise, and every residual is finite (the
    contact field is clamped at its edge).

    Tempering by patches counts a patch's readings as one whatever they say. On two lobes
    0.5 mm apart in radius (three fingers, seed 19) the truth's half-turned image was
    declared at 99.9 %: on the leader's 64 readings, counted independent, the truth fitted
    82 worse in chi-square than the declared pose; weighed so, each pose fitted, 5.3
    better."""
    sd = np.broadcast_to(np.asarray(sd, dtype=np.float64), (len(points),))
    cov = (np.diag(sd**2) + ctx.sigma**2
           + shared_error(points, ctx.mismatch_sd, correlation_length(ctx.mismatch_length)))
    chol = cholesky(cov, lower=True)
    fitted = [whitened_fit(ctx.field, pose, points, radii, chol, iterations,
                           max_move=0.25 * ctx.scale) for pose in poses]
    return (np.array([pose for pose, _ in fitted]).reshape(-1, 3),
            np.array([chi2 for _, chi2 in fitted]))


def offset_refit(ctx: ObjectContext, points: np.ndarray, radii: np.ndarray, sd: np.ndarray,
                  fit: Fit, outliers: int) -> Fit:
    """`fit` refined again with the outline moved by the one offset its residuals share
    (as `offset_log_likelihood`), so that its residuals are judged without it; its spread
    widened by their rms where that exceeds the sensor's sd, as the readings then say the
    error is larger than the model thought. Before, a world off the model alike under every
    fingertip left the largest residual just beyond the rule's limit for good (blob:27,
    seed 27, three fingers: 4.5 sd against 3.6, undecided after 60 steps, 0.25 degrees
    off)."""
    if ctx.mismatch_length <= 0:
        return fit
    offset = float(shared_offset(ctx, residuals(ctx.field, np.asarray([fit.pose]), points,
                                                 radii), sd)[0])
    refit = refine(ctx.field, points, radii + offset, np.asarray(fit.pose), sd,
                   max_outliers=outliers)
    if refit.rms > 1.0:
        refit = dataclasses.replace(refit, position_sd=refit.position_sd * refit.rms,
                                    heading_sd=refit.heading_sd * refit.rms)
    return refit


def patch_temper(ctx: ObjectContext, points: np.ndarray) -> float:
    """How much of the readings' log likelihood is independent evidence: the world's outline
    differs from the model coherently over `mismatch_length`, so readings within one such
    patch share their error (a wrong pose 136 degrees off out-fitted the truth by 7 nats on
    11 readings from three small arcs: rounded:14, seed 14). Counted as the distinct
    patches felt per reading."""
    if ctx.mismatch_length <= 0 or len(points) == 0:
        return 1.0
    return min(1.0, distinct_places(points, ctx.mismatch_length) / len(points))


def widened(fit: Fit, temper: float) -> Fit:
    """`fit` with its spread widened for readings that share their error (`patch_temper`): the
    covariance of K readings in K * temper independent patches. (rounded:8, seed 8: a
    heading 5.5 degrees off was declared at a spread of 0.67 degrees from 10 readings on
    three small arcs.)"""
    scale = 1.0 / np.sqrt(max(temper, 1e-6))
    return dataclasses.replace(fit, position_sd=fit.position_sd * scale,
                               heading_sd=fit.heading_sd * scale)


def with_shared_error(ctx: ObjectContext, points: np.ndarray, radii: np.ndarray,
                       sd: np.ndarray, fit: Fit) -> Fit:
    """`fit` with its spread at least what the world's coherent difference from the model
    leaves (`contour_fit.correlated_spread`): where the outline tells the heading only
    weakly (a near-circle, an ellipse near its round), readings in a few patches that err
    together turn the fit by degrees. Counting patches (`widened`) missed it: keyed:124,
    seed 124, three fingers, declared 3.6 degrees off at a spread of 0.75 degrees; the
    sandwich says 1.3."""
    if ctx.mismatch_length <= 0 or ctx.mismatch_sd <= 0 or len(points) < 3:
        return fit
    position_sd, heading_sd = correlated_spread(
        ctx.field, points, radii, np.asarray(fit.pose), np.broadcast_to(sd, (len(points),)),
        ctx.mismatch_sd, correlation_length(ctx.mismatch_length))
    return dataclasses.replace(fit, position_sd=max(fit.position_sd, position_sd),
                               heading_sd=max(fit.heading_sd, heading_sd))
