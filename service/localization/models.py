"""Motion and sensor models shared by every localizer (paper §3; STYLE.md item 1).

Hypotheses are start poses (x0, y0, heading) in the map frame. The finger measures its
centre relative to its start, in its own frame, so a hypothesis and a measured
displacement fix where on the map the centre should be (the motion model), and the
measured height change is compared with the contact surface's (the sensor model).
Heights are always relative to the first contact, so the unknown z offset drops out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from service.errors import ConfigError


def rotate(headings: np.ndarray, dx: float | np.ndarray, dy: float | np.ndarray
           ) -> tuple[np.ndarray, np.ndarray]:
    """Finger-frame vector(s) (dx, dy) expressed in the map frame for each heading."""
    c, s = np.cos(headings), np.sin(headings)
    return c * dx - s * dy, s * dx + c * dy


class MotionModel(Protocol):
    """Where each start-pose hypothesis puts the centre after a measured displacement."""

    def positions(self, poses: np.ndarray, displacement: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Map (x, y) of the centre for poses (N, 3) and a finger-frame displacement (2,)."""

    @property
    def position_sigma(self) -> float:
        """Standard deviation (metres) of a predicted centre position along each axis."""


class SensorModel(Protocol):
    """How well a measured relative height fits a predicted one."""

    def log_likelihood(self, residual: np.ndarray) -> np.ndarray:
        """Log likelihood (up to a constant) of each height residual (metres)."""

    def consistent(self, residual: np.ndarray) -> np.ndarray:
        """Mask of residuals a hypothesis may have and still be the truth."""

    @property
    def sigma(self) -> float:
        """Standard deviation (metres) of the residual of the true hypothesis, inliers only."""

    @property
    def tolerance(self) -> float:
        """Largest residual (metres) `consistent` accepts."""


@dataclass(frozen=True)
class RigidMotion:
    """The centre moved exactly as measured, up to isotropic measurement noise."""

    measurement_sigma: float = 0.0

    def __post_init__(self) -> None:
        if not self.measurement_sigma >= 0:
            raise ConfigError("measurement_sigma must be >= 0 metres")

    def positions(self, poses: np.ndarray, displacement: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        dx, dy = rotate(poses[:, 2], displacement[0], displacement[1])
        return poses[:, 0] + dx, poses[:, 1] + dy

    @property
    def position_sigma(self) -> float:
        return self.measurement_sigma


@dataclass(frozen=True)
class RobustGaussian:
    """Gaussian residuals plus a uniform outlier floor, gated at `gate` sigmas.

    The floor keeps one bad reading (a slip, a bump the map lacks) from killing the truth.
    """

    sigma_m: float = 1e-7
    outlier_probability: float = 0.0
    outlier_range_m: float = 0.05
    gate: float = 5.0

    def __post_init__(self) -> None:
        if not self.sigma_m > 0:
            raise ConfigError("sensor sigma must be > 0 metres")
        if not 0 <= self.outlier_probability < 1:
            raise ConfigError("outlier_probability must be in [0, 1)")
        if not (self.outlier_range_m > 0 and self.gate > 0):
            raise ConfigError("outlier_range_m and gate must be > 0")

    @property
    def sigma(self) -> float:
        return self.sigma_m

    def log_likelihood(self, residual: np.ndarray) -> np.ndarray:
        z = np.asarray(residual) / self.sigma_m
        inlier = (1 - self.outlier_probability) * np.exp(-0.5 * z * z) / self.sigma_m
        if self.outlier_probability == 0:
            return np.log(np.maximum(inlier, 1e-300))
        return np.log(inlier + self.outlier_probability / self.outlier_range_m)

    @property
    def tolerance(self) -> float:
        return self.gate * self.sigma_m

    def consistent(self, residual: np.ndarray) -> np.ndarray:
        return np.abs(residual) <= self.tolerance


HARDWARE_SENSOR_SIGMA = 0.0002
"""Centre noise (metres) assumed on real servos: encoder rounding (about 0.1 mm at the tip
of the preset hands) times the surface slope. The simulator's noise-free tolerance (0.5 um)
would eliminate the true pose on encoder readings."""


@dataclass(frozen=True)
class NoiseSpec:
    """The noise the finger and world actually have (BENCHMARKS.md B2), all in metres/radians."""

    measurement_sigma: float = 0.0
    step_length_fraction: float = 0.0
    step_direction_sigma: float = 0.0
    surface_sigma: float = 0.0
    surface_correlation: float = 0.01

    def __post_init__(self) -> None:
        for name in ("measurement_sigma", "step_length_fraction", "step_direction_sigma",
                     "surface_sigma"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"noise {name} must be >= 0")
        if not self.surface_correlation > 0:
            raise ConfigError("noise surface_correlation must be > 0")

    @property
    def any(self) -> bool:
        return bool(self.measurement_sigma or self.step_length_fraction
                    or self.step_direction_sigma or self.surface_sigma)

    @property
    def surface_slope_sd(self) -> float:
        """Sd (radians) of the slope the world's mismatch adds to the model's surface: white
        noise smoothed by a Gaussian of sd `surface_correlation` (as the simulator draws
        it) has a slope of sd sigma / (sqrt(2) * correlation)."""
        return float(self.surface_sigma / (np.sqrt(2.0) * self.surface_correlation))

    @classmethod
    def realistic(cls, unit: float = 0.01) -> NoiseSpec:
        """B2's models for a map whose unit is `unit` metres."""
        return cls(measurement_sigma=0.01 * unit, step_length_fraction=0.02,
                   step_direction_sigma=np.deg2rad(1.0), surface_sigma=0.02 * unit,
                   surface_correlation=1.0 * unit)


def models_for(noise: NoiseSpec) -> tuple[RigidMotion, RobustGaussian]:
    """Motion and sensor models matched to a noise level (exact ones when noise-free).

    Residual sigma: the two height readings (now and at first contact) each carry
    measurement noise, the world differs from the map, and position noise times a
    typical slope leaks into height.
    """
    if not noise.any:
        return RigidMotion(0.0), RobustGaussian(sigma_m=1e-7, gate=5.0)
    # Measured on B2 (peaks): the refined fit's residuals are about 0.12 mm while the sum
    # of every term at its worst is 0.35 mm, because the finger's dilation smooths the
    # world's perturbation and the height offset is fitted. 0.2 mm keeps a margin.
    slope = 1.0
    sigma = float(np.sqrt(noise.measurement_sigma**2 + noise.surface_sigma**2 / 2
                          + (slope * noise.measurement_sigma) ** 2))
    return (RigidMotion(noise.measurement_sigma),
            RobustGaussian(sigma_m=sigma, outlier_probability=0.02,
                           outlier_range_m=0.05, gate=5.0))
