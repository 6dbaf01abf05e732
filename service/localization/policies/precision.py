"""What a reading would pin the leading pose by: the spread as the declaration weighs it.

The map differs from the object smoothly, so readings near each other err together: the
declared spread is the least-squares pose's under an error shared with a Gaussian
correlation over a step, besides each reading's own (`refine.correlated_spread`, the
sandwich A^-1 M A^-1). A reading's worth to a declaration is how much it would shrink that
spread: 0.5 log of the ratio of the spread's volumes without and with it, weighted by the
leading mode's probability. Weighed as independent (what the policy did before), it took
the pose to be pinned long before the declaration did: on shells 0.9-2 mm of claimed
spread was left after 60 steps, against the 0.8 mm a declaration needs.

A prior of a step and `PRIOR_HEADING` bounds a direction no reading has seen yet (a
straight rib, a plain), so the readings that would see it are worth the most.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.localization.localizers.fitting import sample
from service.localization.policies.base import PolicyInput
from service.localization.surface import ContactSurface

PRIOR_HEADING = np.deg2rad(30.0)
"""How loose a heading no reading has constrained is taken to be."""


@dataclass(frozen=True)
class Spread:
    """The leading pose's spread from the readings so far, built once per decision; `gain`
    prices a reading at any place against it."""

    read: np.ndarray
    """(K, 2) where the readings so far were taken (finger frame, m)."""
    rows: np.ndarray
    """(K, 4) their sensitivity to (x0, y0, heading, height offset) at the leading pose."""
    normal: np.ndarray
    """(4, 4) A = J^T W J plus the prior."""
    meat: np.ndarray
    """(4, 4) M = J^T W (own + shared covariance) W J plus the prior."""
    volume: float
    """Determinant of the pose block of A^-1 M A^-1: the spread's volume now."""
    s: float
    shared_var: float
    mass: float

    @classmethod
    def now(cls, view: PolicyInput, s: float, read: list[np.ndarray],
            shared_sd: float | None = None) -> Spread | None:
        """The spread of `view`'s leading pose from readings at `read`, each with an own
        error of sd `s` and a shared one of `shared_sd` (default `s`); None before the
        localizer has fitted a pose."""
        est = view.estimate
        if est is None or est.pose is None or est.information is None or not read:
            return None
        step = view.step_length
        shared_var = (s if shared_sd is None else shared_sd) ** 2
        done = np.asarray(read, dtype=np.float64)
        rows, _ = _pose_rows(view.surface, est.pose, done)
        w = 1.0 / s**2
        prior = np.diag([1 / step**2, 1 / step**2, 1 / PRIOR_HEADING**2, 1 / step**2])
        normal = w * rows.T @ rows + prior
        meat = normal + w * w * rows.T @ (shared_var * correlation(done, done, step)) @ rows
        volume = float(_volumes(normal[np.newaxis], meat[np.newaxis])[0])
        mass = float(est.mode_mass) if np.isfinite(est.mode_mass) else 0.0
        return cls(done, rows, normal, meat, volume, s, shared_var, mass)

    def gain(self, view: PolicyInput, offsets: np.ndarray) -> np.ndarray:
        """Expected information (nats) of a reading at each place (`offsets`, steps from
        the finger) about where exactly the leading pose lies; 0 off the map."""
        step, s = view.step_length, self.s
        fresh = (np.asarray(view.displacement, dtype=np.float64)[np.newaxis, :2]
                 + offsets * step)
        jt, on_map = _pose_rows(view.surface, view.estimate.pose, fresh)
        w = 1.0 / s**2
        # a reading at each place added: A + w j j^T, and M gains its row and column of
        # the readings' covariance (its own s^2 and what it shares with each one read)
        u = w * jt
        v = w * (self.shared_var * correlation(fresh, self.read, step)) @ self.rows
        normal = self.normal + w * np.einsum("ti,tj->tij", jt, jt)
        meat = (self.meat + np.einsum("ti,tj->tij", u, v) + np.einsum("ti,tj->tij", v, u)
                + (s**2 + self.shared_var) * np.einsum("ti,tj->tij", u, u))
        after = _volumes(normal, meat)
        gain = 0.5 * np.log(np.maximum(self.volume / np.maximum(after, 1e-300), 1.0))
        return np.where(on_map & np.isfinite(gain), gain * self.mass, 0.0)


def _pose_rows(surface: ContactSurface, pose: tuple[float, float, float],
               places: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P, 4) each reading's sensitivity to (x0, y0, heading, height offset) at `pose`, for
    readings at `places` (finger frame), and whether each lies on the map."""
    x0, y0, heading = pose
    c, si = np.cos(heading), np.sin(heading)
    tx, ty = places[:, 0], places[:, 1]
    x, y = x0 + c * tx - si * ty, y0 + si * tx + c * ty
    _, gx, gy = sample(surface, x, y)
    rows = np.column_stack([gx, gy, gx * (-si * tx - c * ty) + gy * (c * tx - si * ty),
                            -np.ones(len(places))])
    if surface.map.is_profile:  # a profile fits neither y0 nor the direction
        rows[:, 1:3] = 0.0
    return rows, surface.map.inside(x, y)


def correlation(a: np.ndarray, b: np.ndarray, length: float) -> np.ndarray:
    """(A, B) the map error's correlation between readings at places `a` and `b`: Gaussian
    over `length`, as `refine.shared_error` has it."""
    return np.exp(-0.5 * np.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=-1) / length**2)


def _volumes(normal: np.ndarray, meat: np.ndarray) -> np.ndarray:
    """Determinant of the pose block (x0, y0, heading) of the sandwich covariance
    A^-1 M A^-1, for each of a batch of (4, 4) A and M."""
    bread = np.linalg.inv(normal)
    return np.linalg.det((bread @ meat @ bread)[:, :3, :3])
