"""The grasp model (paper §6, Eq. 8): contacts, the grasp map, friction cones, quality.

Fingertips touch the object at points with outward normals n (from the contour under a
pose). Each is a point contact with Coulomb friction mu: the finger pushes with a force in
the cone around -n of half-angle atan(mu) (in the plane the cone has exactly two edges, so
its linearization is exact). Wrenches are (f_x, f_z, torque / rho) about the object's
centroid, rho being the object's largest radius, so forces and torques weigh alike.

Two measures:

* `epsilon` - the Ferrari-Canny measure: the radius of the largest ball about the origin
  inside the convex hull (scipy.spatial.ConvexHull) of the cone edges' wrenches at unit
  normal force. Zero without force closure. Geometry only: it ignores how hard the fingers
  can push and what the object weighs.
* `quality` - what holds the object: the fingers push at most as hard as their joints'
  goal current allows (through the Jacobian, `kinematics.max_tip_force`), so each contact
  can apply a bounded set of forces; the grasp can apply their Minkowski sum. Quality is
  the largest disturbance wrench (newtons) the grasp resists on top of the object's weight,
  negative when it cannot even carry that. The object slips - a drop - when it falls below
  the disturbance margin; the policy keeps it above a threshold.

`quality` runs in the policy's inner loop for every move and plausible pose, so it is one
compiled loop: the distance from the load to the boundary of a Minkowski sum of polygons is
the least, over the sum's facet normals, of the support function minus the load's
projection; every facet normal is a polygon's own plane's or the cross product of edges of
two different polygons (`_margins`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial import ConvexHull, QhullError

from firmware_if.kinematics import Chain
from firmware_if.registers import NEWTON_METRES_PER_AMP
from service.errors import ConfigError
from service.localization import chain_kernels
from service.localization.objects import corners, kinks
from service.localization.objects.field import ContactField
from service.localization.objects.rolling import contacts

GRAVITY = 9.81


@dataclass(frozen=True)
class GraspSpec:
    """Friction, load and the quality the grasp must keep. Newtons, kilograms."""

    mu: float = 0.5
    mass_kg: float = 0.05
    margin_n: float = 0.2
    """Disturbance (wrench norm) the grasp must resist beyond the weight; below it the
    object slips out."""
    threshold_n: float = 1.0
    """Quality a move must keep, predicted over every plausible pose (at least the margin)."""
    start_n: float | None = None
    """Quality the hand's first grasp is known to have, at least the threshold (None: the
    threshold): the handover is set up to give at least this, and the policy relies on it.
    Poses that explain the first readings run on until the grasp under them would be this
    weak, so at the threshold itself every move of two fingers takes one of them below it
    and they rarely move (rounded:2, seed 2). A firmer start lets them move, but they do
    not yet move safely: at 2 N, 7 of 400 two-finger runs on members 100-199 dropped."""

    def __post_init__(self) -> None:
        for name, value in (("friction coefficient mu", self.mu), ("object mass", self.mass_kg),
                            ("disturbance margin", self.margin_n),
                            ("grasp quality threshold", self.threshold_n),
                            ("start grasp quality", self.start_n)):
            if value is not None and not math.isfinite(value):
                raise ConfigError(f"{name} must be a finite number, got {value}")
        if not self.mu > 0:
            raise ConfigError(f"friction coefficient mu must be > 0, got {self.mu}")
        if not self.mass_kg >= 0:
            raise ConfigError(f"object mass must be >= 0 kg, got {self.mass_kg}")
        if not self.margin_n >= 0:
            raise ConfigError(f"disturbance margin must be >= 0 N, got {self.margin_n}")
        if not self.threshold_n >= self.margin_n:
            raise ConfigError(f"grasp quality threshold ({self.threshold_n} N) must be at "
                              f"least the disturbance margin ({self.margin_n} N)")
        if self.start_n is not None and not self.start_n >= self.threshold_n:
            raise ConfigError(f"start grasp quality ({self.start_n} N) must be at least the "
                              f"threshold ({self.threshold_n} N)")

    @property
    def start_quality_n(self) -> float:
        """The quality the first grasp is known to have (`start_n`, else the threshold)."""
        return self.threshold_n if self.start_n is None else self.start_n

    @property
    def load(self) -> np.ndarray:
        """The wrench the contacts must supply: the weight's opposite, at the centroid."""
        return np.array([0.0, self.mass_kg * GRAVITY, 0.0])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def tangents(normals: np.ndarray) -> np.ndarray:
    """Unit tangents, the normals turned a quarter counter-clockwise."""
    return np.stack([-normals[..., 1], normals[..., 0]], axis=-1)


def grasp_map(points: np.ndarray, normals: np.ndarray, origin: np.ndarray, rho: float
              ) -> np.ndarray:
    """G (3, 2n) of paper Eq. 8: the object wrench of finger forces given per contact as
    (pushing along -n, along the tangent)."""
    directions = np.stack([-normals, tangents(normals)], axis=1)  # (n, 2, 2)
    lever = points - origin
    torque = _cross(lever[:, None, :], directions) / rho  # (n, 2)
    return np.concatenate([directions, torque[..., None]], axis=-1).reshape(-1, 3).T


def cone_edges(normals: np.ndarray, mu: float) -> np.ndarray:
    """(n, 2, 2): the two edges of each friction cone, as forces of unit normal part."""
    t = tangents(normals)
    return np.stack([-normals - mu * t, -normals + mu * t], axis=1)


def wrenches(points: np.ndarray, forces: np.ndarray, origin: np.ndarray, rho: float
             ) -> np.ndarray:
    """(..., 3) wrenches of forces (..., 2) applied at points (..., 2)."""
    torque = _cross(points - origin, forces) / rho
    return np.concatenate([forces, torque[..., None]], axis=-1)


def epsilon(points: np.ndarray, normals: np.ndarray, origin: np.ndarray, rho: float,
            mu: float) -> float:
    """Ferrari-Canny epsilon (L1): the largest ball about the origin inside the hull of the
    cone edges' wrenches at unit normal force; 0 without force closure."""
    w = wrenches(points[:, None, :], cone_edges(normals, mu), origin, rho).reshape(-1, 3)
    try:
        hull = ConvexHull(w)
    except (QhullError, ValueError):  # too few or flat wrenches: no closure
        return 0.0
    offsets = hull.equations[:, 3]  # unit normals: a.x + offset <= 0 inside
    return float(max(0.0, np.min(-offsets)))


def force_vertices(normals: np.ndarray, mu: float, limits: np.ndarray) -> np.ndarray:
    """(..., n, 3, 2): the forces at the corners of what each contact can push with - along
    each cone edge and straight in, as far as the finger's joints allow (`limits`,
    (..., n, 3) newtons along those unit directions)."""
    edges = cone_edges(normals.reshape(-1, 2), mu).reshape(*normals.shape[:-1], 2, 2)
    edges = edges / np.linalg.norm(edges, axis=-1, keepdims=True)
    directions = np.stack([edges[..., 0, :], -normals, edges[..., 1, :]], axis=-2)
    return directions * limits[..., None]


@numba.njit(cache=True, nogil=True)
def _forces(normals: np.ndarray, jac: np.ndarray, torque: float, mu: float) -> np.ndarray:
    """`force_vertices` (B, n, 3, 2) with each finger's limits along the unit directions
    (`kinematics.max_tip_force`): `jac` (B or 1, n, 3, joints) is each finger's Jacobian
    at its joint angles, zero-padded to the most joints."""
    batch, n, joints = normals.shape[0], normals.shape[1], jac.shape[3]
    out = np.empty((batch, n, 3, 2))
    for b in range(batch):
        jb = 0 if jac.shape[0] == 1 else b
        for i in range(n):
            nx, nz = normals[b, i, 0], normals[b, i, 1]
            for v in range(3):
                if v == 1:  # straight in
                    dx, dz = -nx, -nz
                else:  # a cone edge, -n -/+ mu t with t = (-nz, nx), made unit
                    sign = -1.0 if v == 0 else 1.0
                    dx, dz = -nx + sign * (mu * -nz), -nz + sign * (mu * nx)
                    norm = math.sqrt(dx * dx + dz * dz)
                    dx, dz = dx / norm, dz / norm
                most = 0.0
                for j in range(joints):
                    most = max(most, abs(dx * jac[jb, i, 0, j] + dz * jac[jb, i, 2, j]))
                bound = torque / max(most, 1e-12)
                out[b, i, v, 0] = dx * bound
                out[b, i, v, 1] = dz * bound
    return out


@numba.njit(cache=True, nogil=True)
def _corners(points: np.ndarray, origins: np.ndarray, forces: np.ndarray, rho: float,
             b: int, vertices: np.ndarray) -> None:
    """Grasp b's contacts' wrench polygons' corners into `vertices` (n, k + 1, 3); corner 0
    is the zero wrench."""
    for i in range(forces.shape[1]):
        rx = points[b, i, 0] - origins[b, 0]
        rz = points[b, i, 1] - origins[b, 1]
        for v in range(forces.shape[2]):
            fx, fz = forces[b, i, v, 0], forces[b, i, v, 1]
            vertices[i, v + 1, 0] = fx
            vertices[i, v + 1, 1] = fz
            vertices[i, v + 1, 2] = (rx * fz - rz * fx) / rho


@numba.njit(cache=True, nogil=True)
def _gap(ux: float, uy: float, uz: float, vertices: np.ndarray, load: np.ndarray,
         best: float) -> float:
    """The least of `best` and h(u) - u.load and h(-u) + u.load for a candidate facet
    normal u (unit), h the support function of the Minkowski sum of the polygons."""
    up, down = 0.0, 0.0
    for i in range(vertices.shape[0]):
        top, bottom = 0.0, 0.0  # the zero force is a corner of every polygon
        for v in range(1, vertices.shape[1]):
            p = ux * vertices[i, v, 0] + uy * vertices[i, v, 1] + uz * vertices[i, v, 2]
            top = max(top, p)
            bottom = max(bottom, -p)
        up += top
        down += bottom
    along = ux * load[0] + uy * load[1] + uz * load[2]
    return min(best, up - along, down + along)


@numba.njit(cache=True, nogil=True)
def _normal_gap(e: np.ndarray, f: np.ndarray, vertices: np.ndarray, load: np.ndarray,
                best: float) -> float:
    """`_gap` for the normal of edges e and f (3,); `best` when they are parallel."""
    ux = e[1] * f[2] - e[2] * f[1]
    uy = e[2] * f[0] - e[0] * f[2]
    uz = e[0] * f[1] - e[1] * f[0]
    norm = math.sqrt(ux * ux + uy * uy + uz * uz)
    if norm < 1e-12:
        return best
    return _gap(ux / norm, uy / norm, uz / norm, vertices, load, best)


@numba.njit(cache=True, nogil=True)
def _plane_gap(edges: np.ndarray, count: int, vertices: np.ndarray, load: np.ndarray,
               best: float) -> float:
    """`_gap` for the normal of a polygon's own plane: its first edge crossed with the
    first edge not parallel to it."""
    for e2 in range(1, count):
        f = edges[e2]
        e = edges[0]
        ux = e[1] * f[2] - e[2] * f[1]
        uy = e[2] * f[0] - e[0] * f[2]
        uz = e[0] * f[1] - e[1] * f[0]
        if math.sqrt(ux * ux + uy * uy + uz * uz) >= 1e-12:
            return _normal_gap(e, f, vertices, load, best)
    return best


@numba.njit(cache=True, nogil=True)
def _hull_edges(forces: np.ndarray, b: int, i: int, vertices: np.ndarray, edges: np.ndarray
                ) -> int:
    """Contact i's polygon's edges (the hull of zero and its force corners) into `edges`,
    as corner c minus corner a (a < c); how many. A pair of corners is kept unless other
    corners lie clearly on both sides of the line through them (a diagonal): near-collinear
    corners keep every pair they could form, so no edge is ever missed."""
    k = forces.shape[2]
    m = 0
    for a in range(k + 1):
        ax = 0.0 if a == 0 else forces[b, i, a - 1, 0]
        az = 0.0 if a == 0 else forces[b, i, a - 1, 1]
        for c in range(a + 1, k + 1):
            dx, dz = forces[b, i, c - 1, 0] - ax, forces[b, i, c - 1, 1] - az
            scale = dx * dx + dz * dz
            left, right = False, False
            for o in range(k + 1):
                if o in (a, c):
                    continue
                ox = (0.0 if o == 0 else forces[b, i, o - 1, 0]) - ax
                oz = (0.0 if o == 0 else forces[b, i, o - 1, 1]) - az
                side = dx * oz - dz * ox
                tol = 1e-9 * math.sqrt(scale * (ox * ox + oz * oz))
                left |= side > tol
                right |= side < -tol
            if not (left and right):
                for d in range(3):
                    edges[i, m, d] = vertices[i, c, d] - vertices[i, a, d]
                m += 1
    return m


@numba.njit(cache=True, nogil=True)
def _every_pair(vertices: np.ndarray, load: np.ndarray) -> float:
    """The least gap over the normals of every pair of corner differences of every polygon:
    a superset of the sum's facet normals, whatever the grasp."""
    n, corners = vertices.shape[0], vertices.shape[1]
    per = corners * (corners - 1) // 2
    edges = np.empty((n * per, 3))
    m = 0
    for i in range(n):
        for a in range(corners):
            for c in range(a + 1, corners):
                for d in range(3):
                    edges[m, d] = vertices[i, c, d] - vertices[i, a, d]
                m += 1
    best = np.inf
    for e1 in range(m):
        for e2 in range(e1 + 1, m):
            best = _normal_gap(edges[e1], edges[e2], vertices, load, best)
    return best


@numba.njit(cache=True, nogil=True)
def _margins(points: np.ndarray, origins: np.ndarray, forces: np.ndarray, rho: float,
             load: np.ndarray) -> np.ndarray:
    """Per grasp b: min over candidate facet normals u of h(u) - u.load, where h is the
    support function of the Minkowski sum of the contacts' wrench polygons (each the hull
    of zero and its force corners).

    Each polygon lies in a plane through zero, so a facet of the sum is either a translate
    of one polygon (normal: that plane's) or spanned by edges of two different polygons
    (normal: their cross product). Those normals are tried first; when the least gap over
    them is positive the load is inside the sum and that gap is its distance to the
    boundary, as over any superset. Otherwise (the grasp cannot carry the load) the value
    is the least over every pair of corner differences (`_every_pair`), as it always was:
    outside the sum the least depends on which normals are tried."""
    batch, n, k = forces.shape[0], forces.shape[1], forces.shape[2]
    vertices = np.zeros((n, k + 1, 3))
    edges = np.empty((n, (k + 1) * k // 2, 3))
    counts = np.empty(n, dtype=np.int64)
    out = np.empty(batch)
    for b in range(batch):
        _corners(points, origins, forces, rho, b, vertices)
        best = np.inf
        for i in range(n):
            counts[i] = _hull_edges(forces, b, i, vertices, edges)
            best = _plane_gap(edges[i], counts[i], vertices, load, best)
        for i in range(n):
            for j in range(i + 1, n):
                for e1 in range(counts[i]):
                    for e2 in range(counts[j]):
                        best = _normal_gap(edges[i, e1], edges[j, e2], vertices, load, best)
        out[b] = best if best > 1e-12 else _every_pair(vertices, load)
    return out


def quality(points: np.ndarray, origins: np.ndarray, forces: np.ndarray, rho: float,
            load: np.ndarray) -> np.ndarray:
    """Largest disturbance (newtons, wrench norm) each grasp resists on top of `load`;
    negative when it cannot carry the load. `points` (..., n, 2) contact points, `origins`
    (..., 2) object centroids, `forces` (..., n, k, 2) each contact's force corners."""
    shape = points.shape[:-2]
    n = points.shape[-2]
    out = _margins(np.ascontiguousarray(points, dtype=np.float64).reshape(-1, n, 2),
                   np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 2),
                   np.ascontiguousarray(forces, dtype=np.float64).reshape(
                       -1, n, forces.shape[-2], 2),
                   float(rho), np.ascontiguousarray(load, dtype=np.float64))
    return out.reshape(shape)


def joint_torque(goal_current_a: float, model: str) -> float:
    """N m a joint pushes with at its goal-current bound."""
    return goal_current_a * NEWTON_METRES_PER_AMP[model]


def hand_quality(field: ContactField, poses: np.ndarray, centres: np.ndarray,
                 fingers: Sequence[Chain], joint_angles: Sequence[np.ndarray], torque: float,
                 spec: GraspSpec, tilt: float = 0.0, beside_kinks: bool = False,
                 least: bool = False, beside_corners: bool = False) -> np.ndarray:
    """Quality (B,) of fingertips at `centres` (B, n, 2) holding the object under `poses`
    (B, 3), finger i at joint angles `joint_angles[i]` ((B, joints) or (joints,)).

    `tilt` > 0: the most the grasp could have in a world whose outline turns each contact's
    normal up to `tilt` radians from the model's - the best of the model's normals and of
    every finger's turned by -tilt or +tilt (2^n ways). What the model says of a grasp in
    the world is only that good: the quality turns on where the normals point. With `least`,
    the worst of those ways instead: what the world may make of it at its worst.

    `beside_kinks`: where a tip lies beside a kink of the dilated contour (a hollow narrower than
    the tip, `objects.kinks`), the world may rest it on either side or bridging: the most
    the grasp could have with that finger's normal any of the three, as well (with `least`,
    the least). `beside_corners`: likewise where a tip lies near a sharp convex corner,
    whose vertex the world may put it on (`objects.corners`)."""
    radii = np.array([f.radius for f in fingers])
    points, normals = contacts(field, poses, centres, radii)
    angles = [np.asarray(q, dtype=np.float64) for q in joint_angles]
    rows = max((len(q) for q in angles if q.ndim == 2), default=1)
    jac = np.zeros((rows, len(fingers), 3, max(q.shape[-1] for q in angles)))
    for i, (finger, q) in enumerate(zip(fingers, angles, strict=True)):
        jac[:, i, :, :q.shape[-1]] = chain_kernels.jacobians(finger, q.reshape(-1, q.shape[-1]))
    ways = 1
    if tilt > 0:  # every way's normals after the model's own, stacked along the batch
        n = len(fingers)
        turns = tilt * np.array([[0.0] * n, *itertools.product((-1.0, 1.0), repeat=n)])
        ways = len(turns)
        c, s = np.cos(turns)[:, None], np.sin(turns)[:, None]  # (ways, 1, n)
        normals = np.stack([c * normals[..., 0] - s * normals[..., 1],
                            s * normals[..., 0] + c * normals[..., 1]], axis=-1)
        normals = normals.reshape(-1, n, 2)
        points, poses = np.tile(points, (ways, 1, 1)), np.tile(poses, (ways, 1))
        jac = np.tile(jac, (ways, 1, 1, 1)) if rows > 1 else jac
    margins = quality(points, poses[:, :2], _forces(normals, jac, float(torque),
                                                     float(spec.mu)),
                      field.contour.max_radius, spec.load)
    margins = margins.reshape(ways, -1)
    margins = margins.min(axis=0) if least else margins.max(axis=0)
    own = slice(0, len(margins))  # the model's own normals come first of a tilt's ways
    finders = [find for find, asked in ((kinks.beside, beside_kinks),
                                        (corners.beside, beside_corners)) if asked]
    for find in finders:
        _rest_elsewhere(find, field, poses[own], centres, points[own], normals[own], radii,
                        jac[own] if jac.shape[0] > 1 else jac, torque, spec, margins, least)
    return margins


def _rest_elsewhere(find: Callable, field: ContactField, poses: np.ndarray,
                    centres: np.ndarray, points: np.ndarray, normals: np.ndarray,
                    radii: np.ndarray, jac: np.ndarray, torque: float, spec: GraspSpec,
                    margins: np.ndarray, least: bool = False) -> None:
    """`margins` (B,) raised to the quality of every other way `find` (`kinks.beside`,
    `corners.beside`) says a tip may rest, one finger at a time (with `least`, lowered to
    it)."""
    rows, finger, alternatives = find(field.contour, poses, centres, radii)
    if len(rows) == 0:
        return
    ways = alternatives.shape[1]
    rows, finger = np.repeat(rows, ways), np.repeat(finger, ways)
    varied = normals[rows].copy()  # (3m, n, 2)
    varied[np.arange(len(rows)), finger] = alternatives.reshape(-1, 2)
    at = points[rows].copy()
    at[np.arange(len(rows)), finger] = (centres[rows, finger]
                                         - radii[finger, None] * alternatives.reshape(-1, 2))
    q = quality(at, poses[rows, :2], _forces(varied, jac[rows] if jac.shape[0] > 1 else jac,
                                             float(torque), float(spec.mu)),
                field.contour.max_radius, spec.load)
    (np.minimum if least else np.maximum).at(margins, rows, q)
