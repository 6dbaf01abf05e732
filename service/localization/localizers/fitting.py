"""Array maths shared by the probabilistic localizers: how well start poses fit a history.

Every function works on many hypotheses at once (STYLE.md item 2); the loops themselves are
compiled (`kernels.py`), these wrappers give them surfaces and shapes. A *history* is the
(K + 1, 3) array of finger-frame displacements (dx, dy, dz) since first contact, row 0
being the first contact itself (zeros). For a start pose (x0, y0, heading), reading k
predicts the centre height C(p0 + R(heading) (dx_k, dy_k)) - C(p0) relative to the first
contact; the residual is that minus dz_k. Lookups are bilinear, like `ContactSurface.lookup`,
but also give the gradient, which the Gauss-Newton polish and the least-squares fit need.
"""

from __future__ import annotations

import weakref

import numpy as np
from scipy import ndimage

from service.localization import kernels
from service.localization.surface import ContactSurface

_SLOPES: weakref.WeakKeyDictionary[ContactSurface, float] = weakref.WeakKeyDictionary()


def sample(surface: ContactSurface, x: np.ndarray, y: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre height and its gradient (d/dx, d/dy) at (x, y), bilinear, clamped at the edge."""
    x = np.asarray(x, dtype=np.float64)
    y = np.broadcast_to(np.asarray(y, dtype=np.float64), x.shape)
    value, gx, gy = kernels.sample(surface.centre_heights, surface.map.spacing,
                                   _rows(x.ravel()), _rows(y.ravel()))
    return value.reshape(x.shape), gx.reshape(x.shape), gy.reshape(x.shape)


def typical_slope(surface: ContactSurface) -> float:
    """RMS gradient of the contact surface: converts a pose range into a height range."""
    cached = _SLOPES.get(surface)
    if cached is None:
        grid, spacing = surface.centre_heights, surface.map.spacing
        gx = np.gradient(grid, spacing, axis=1)
        gy = 0.0 if surface.map.is_profile else np.gradient(grid, spacing, axis=0)
        _SLOPES[surface] = cached = max(float(np.sqrt(np.mean(gx**2 + gy**2))), 1e-3)
    return cached


STEEP_BLOCK = 4
"""Samples per side of a block of `steepest_near`'s grid."""
_STEEPEST: weakref.WeakKeyDictionary[ContactSurface, dict[float, np.ndarray]] = (
    weakref.WeakKeyDictionary())


def steepest_near(surface: ContactSurface, radius: float) -> np.ndarray:
    """A coarse grid over the surface (blocks of `STEEP_BLOCK` samples a side): the
    steepest gradient within `radius` metres of each block. A pose that may lie `radius`
    from where a hypothesis puts it reads a height off by at most this times the distance:
    the local bound the global sweep widens its cells by (a global slope is wrong both on
    plains and on a boss's flank)."""
    per_surface = _STEEPEST.setdefault(surface, {})
    if radius not in per_surface:
        grid, spacing = surface.centre_heights, surface.map.spacing
        gx = np.gradient(grid, spacing, axis=1)
        gy = 0.0 if surface.map.is_profile else np.gradient(grid, spacing, axis=0)
        k = max(1, int(np.ceil(radius / spacing)))
        size = (1, 2 * k + 1) if surface.map.is_profile else (2 * k + 1, 2 * k + 1)
        steep = ndimage.maximum_filter(np.hypot(gx, gy), size=size, mode="nearest")
        # one value per block of STEEP_BLOCK samples a side (their largest): a grid small
        # enough to stay in cache, read by nearest block
        b = STEEP_BLOCK
        rows, cols = steep.shape
        padded = np.pad(steep, ((0, -rows % b if rows > 1 else 0), (0, -cols % b)), mode="edge")
        r_blocks = padded.shape[0] // b if rows > 1 else 1
        steep = padded.reshape(r_blocks, -1, padded.shape[1] // b, b).max(axis=(1, 3))
        steep = np.ascontiguousarray(steep)
        steep.setflags(write=False)
        per_surface[radius] = steep
    return per_surface[radius]


def residuals(surface: ContactSurface, poses: np.ndarray, readings: np.ndarray,
              margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Height residuals (N, K) of `readings` (K, 3), the rows after first contact, relative
    to each pose's own first-contact height, and whether each lies on the map."""
    return kernels.relative_residuals(*_surface_args(surface), _rows(poses), _rows(readings),
                                      margin)


def sigmas(sensor_sigma: float, slope: float, history: np.ndarray, pos_range: float,
           head_range: float) -> np.ndarray:
    """Residual sd per reading (K,) for hypotheses that each stand for a range of poses.

    A pose off by `pos_range` metres and `head_range` radians puts reading k off by up to
    pos_range + |d_k| head_range, which a slope turns into height (paper Eq. 4).
    """
    lever = np.hypot(history[:, 0], history[:, 1])
    spread = slope * (pos_range + lever * head_range)
    return np.sqrt(sensor_sigma**2 + spread**2)


def log_likelihood(residual: np.ndarray, on_map: np.ndarray, sigma: np.ndarray,
                   outlier_probability: float, outlier_range: float) -> np.ndarray:
    """Per hypothesis (row), the sum over readings of a Gaussian-plus-uniform log
    likelihood at sd `sigma` (K,); an off-map reading fails (-1000)."""
    if np.ndim(sigma) == 0:
        sigma = np.full(residual.shape[-1], sigma, dtype=np.float64)
    if np.shape(sigma) != (residual.shape[-1],):  # the kernel would read past its end
        raise ValueError(f"{np.shape(sigma)} sds for {residual.shape[-1]} readings")
    return kernels.log_likelihood(_rows(residual), _rows(on_map, np.bool_), _rows(sigma),
                                  float(outlier_probability), float(outlier_range))


def fit_log_likelihood(surface: ContactSurface, poses: np.ndarray, history: np.ndarray,
                       sd: float, margin: float, outlier_probability: float,
                       outlier_range: float) -> np.ndarray:
    """Log likelihood of each pose (N, 3) on every reading at one sd, the height offset
    fitted; a pose whose score is not finite gets -inf (it can never lead)."""
    r, ok = offset_residuals(surface, poses, history, margin)
    ll = log_likelihood(r, ok, sd, outlier_probability, outlier_range)
    return np.where(np.isfinite(ll), ll, -np.inf)


def gauss_newton(surface: ContactSurface, poses: np.ndarray, history: np.ndarray,
                 weights: np.ndarray, iterations: int = 3, damping: float = 1e-4,
                 max_move: float | None = None) -> np.ndarray:
    """A few damped Gauss-Newton steps for every pose at once, with a free height offset.

    Minimizes sum_k w_k (C(p_k) - c - dz_k)^2 over (x0, y0, heading, c) with c eliminated,
    so the first reading is just another noisy reading. Steps are capped at `max_move`
    metres (and max_move / lever radians) so a pose never jumps to another basin.
    """
    history = _rows(history)
    lever = max(float(np.max(np.hypot(history[:, 0], history[:, 1]))), max_move or 0.0)
    return kernels.gauss_newton(surface.centre_heights, surface.map.spacing, _rows(poses),
                                history, _rows(weights), iterations,
                                damping, max_move or 0.0, lever, surface.map.is_profile,
                                surface.map.extent)


def unanchored(anchored: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """Start poses (N, 3) of poses held by where they put the reading-frame point `anchor`
    (x, y) and their heading: how the sweep's cells and the certificate's boxes, anchored
    at a reading or the readings' centroid, become poses of the pool."""
    c, s = np.cos(anchored[:, 2]), np.sin(anchored[:, 2])
    starts = anchored.copy()
    starts[:, 0] -= c * anchor[0] - s * anchor[1]
    starts[:, 1] -= s * anchor[0] + c * anchor[1]
    return starts


def on_pose_space(surface: ContactSurface, poses: np.ndarray) -> np.ndarray:
    """`poses` (N, 3) as poses the surface allows: on a profile the start lies on the
    profile (y0 = 0) and faces along it, one way or the other (heading 0 or pi)."""
    if not surface.map.is_profile:
        return poses
    out = np.array(poses, dtype=np.float64)
    out[:, 1] = 0.0
    out[:, 2] = np.where(np.cos(out[:, 2]) >= 0, 0.0, np.pi)
    return out


def heights_and_jacobian(surface: ContactSurface, pose: np.ndarray, history: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """For one start pose (3,): the centre height under each reading (K,) and its
    derivatives by (x0, y0, heading) (K, 3)."""
    return kernels.heights_and_jacobian(surface.centre_heights, surface.map.spacing,
                                        _rows(pose), _rows(history))


def slope_squares(surface: ContactSurface, poses: np.ndarray, history: np.ndarray
                  ) -> np.ndarray:
    """For every start pose (N, 3): the squared slope under each reading (N, K)."""
    return kernels.slope_squares(surface.centre_heights, surface.map.spacing, _rows(poses),
                                 _rows(history))


def offset_residuals(surface: ContactSurface, poses: np.ndarray, history: np.ndarray,
                     margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (N, K) of every reading, first contact included, with the height offset
    between hand and map fitted per pose (so no single reading is the exact reference)."""
    return kernels.offset_residuals(*_surface_args(surface), _rows(poses), _rows(history),
                                    margin)


def _surface_args(surface: ContactSurface) -> tuple[np.ndarray, float, tuple[float, float], bool]:
    return (surface.centre_heights, surface.map.spacing, surface.map.extent,
            surface.map.is_profile)


def _rows(a: np.ndarray, dtype: type = np.float64) -> np.ndarray:
    """A C-contiguous, writeable array of `dtype`: the one array type the kernels are
    compiled for (`kernels.warm_up`), so no call compiles a new variant inside a deadline.
    (Checked by hand: `np.require` costs more than most kernels' work.)"""
    if (isinstance(a, np.ndarray) and a.dtype == dtype and a.flags.c_contiguous
            and a.flags.writeable):
        return a
    return np.array(a, dtype=dtype, order="C")
