"""What fingertip readings would pin a held object's leading pose by, as the declaration
weighs the spread: the hand's counterpart of `precision.py`.

The world's outline differs from the model's smoothly, so readings near each other on the
contour err together, and the declared spread is the least-squares pose's sandwich
covariance A^-1 M A^-1 under that shared error (`contour_fit.correlated_spread`). A reading
is worth 0.5 log of the ratio of the spread's volumes without and with it. Weighed as
independent (the policy's mutual information among the plausible poses), a re-read of
contour already felt looked as good as new contour: three fingers on keyed:71 rolled back
and forth over the same arcs for 60 steps while the heading's sd stayed at 1.4 degrees,
over the 1.2 a declaration asks, and a turn (three new places at once) was rarely taken.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.localization.localizers.object_tracks import from_object
from service.localization.objects import kernels
from service.localization.objects.field import ContactField
from service.localization.policies.precision import correlation

PRIOR_HEADING = np.deg2rad(30.0)
"""How loose a heading no reading has constrained is taken to be."""


@dataclass(frozen=True)
class ContourSpread:
    """The leading pose's spread from the readings so far, built once per decision; `gain`
    prices new readings against it."""

    field: ContactField
    pose: np.ndarray
    """(3,) the leading pose."""
    places: np.ndarray
    """(K, 2) object-frame fingertip centres read so far."""
    rows: np.ndarray
    """(K, 3) their residuals' derivatives by the pose (x, z, heading)."""
    normal: np.ndarray
    """(3, 3) A = J^T W J plus the prior."""
    meat: np.ndarray
    """(3, 3) M = J^T W (own + shared covariance) W J plus the prior."""
    volume: float
    s: float
    shared_sd: float
    length: float

    @classmethod
    def now(cls, field: ContactField, pose: np.ndarray, places: np.ndarray,
            radii: np.ndarray, s: float, shared_sd: float, length: float,
            scale: float) -> ContourSpread:
        """The spread of `pose` from readings at object-frame `places` (K, 2) by tips of
        `radii` (K,), each with an own error of sd `s` and a shared one of sd `shared_sd`
        correlated over `length` (Gaussian); `scale` (metres) bounds a position no reading
        has seen yet."""
        rows = _rows(field, pose, places, radii)
        w = 1.0 / s**2
        prior = np.diag([1 / scale**2, 1 / scale**2, 1 / PRIOR_HEADING**2])
        normal = w * rows.T @ rows + prior
        if length <= 0:  # no shared error to correlate
            shared_sd, length = 0.0, 1.0
        shared = shared_sd**2 * correlation(places, places, length)
        meat = normal + w * w * rows.T @ shared @ rows
        return cls(field, np.asarray(pose, dtype=np.float64), places, rows, normal, meat,
                   float(_volume(normal, meat)), s, shared_sd, length)

    def gain(self, places: np.ndarray, radii: np.ndarray, moved: np.ndarray | None = None
             ) -> float:
        """Nats by which readings at object-frame `places` (m, 2) by tips of `radii` (m,)
        together would shrink the spread, after the object is carried to them with a
        motion error of covariance `moved` (3, 3) if any: every reading before it then
        errs by that motion too, against the pose it is read at (a turn taken for three
        new places at once costs what its rolling adds to the spread)."""
        rows = _rows(self.field, self.pose, places, radii)
        w = 1.0 / self.s**2
        u = w * rows  # W j for each new reading
        v = w * (self.shared_sd**2 * correlation(places, self.places, self.length)) @ self.rows
        among = (self.s**2 * np.eye(len(places))
                 + self.shared_sd**2 * correlation(places, places, self.length))
        normal = self.normal + w * rows.T @ rows
        meat = self.meat + u.T @ v + v.T @ u + u.T @ among @ u
        if moved is not None:  # the readings before share the motion's error
            before = w * self.rows.T @ self.rows
            meat = meat + before @ moved @ before
        after = _volume(normal, meat)
        if not (np.isfinite(after) and after > 0):
            return 0.0
        return float(max(0.5 * np.log(self.volume / after), 0.0))


def _rows(field: ContactField, pose: np.ndarray, places: np.ndarray, radii: np.ndarray
          ) -> np.ndarray:
    """(K, 3) the residual's derivatives by the pose of readings at object-frame places."""
    world = from_object(places, pose)
    _, jac = kernels.residuals_and_jacobian(
        *field.args, np.ascontiguousarray(pose, dtype=np.float64),
        np.ascontiguousarray(world), np.ascontiguousarray(radii, dtype=np.float64))
    return jac


def _volume(normal: np.ndarray, meat: np.ndarray) -> float:
    """Determinant of the sandwich covariance A^-1 M A^-1."""
    bread = np.linalg.inv(normal)
    return float(np.linalg.det(bread @ meat @ bread))
