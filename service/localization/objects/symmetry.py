"""Turns under which an object looks (almost) the same: the rivals a declaration must beat.

A rigid motion that maps a bounded contour onto itself fixes its centroid, so in the plane
it is a turn about the centroid. Under an exact symmetry (an ellipse's half turn) two poses
explain every reading equally and no exploration can decide; under a near symmetry (the
`keyed` shapes) they differ only where one feature is. A bounded hypothesis pool may never
have sampled the rotated pose, so localizers test these images of their leading pose
explicitly before declaring it (as `localizers/symmetry.py` does for periodic maps).
"""

from __future__ import annotations

import numpy as np

from service.localization.memo import kept
from service.localization.objects.field import ContactField


def _mismatch(field: ContactField, points: np.ndarray, motions: np.ndarray,
              coverage: float) -> np.ndarray:
    """Per motion (A, 3) = (turn, shift u, shift v), the `coverage` quantile of |distance|
    of the moved outline's points (A,)."""
    d, _, _ = field.distance(*_moved(points, motions))
    return np.quantile(np.abs(d), coverage, axis=1)


def _moved(points: np.ndarray, motions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c, s = np.cos(motions[:, :1]), np.sin(motions[:, :1])
    u = c * points[None, :, 0] - s * points[None, :, 1] + motions[:, 1:2]
    v = s * points[None, :, 0] + c * points[None, :, 1] + motions[:, 2:3]
    return u, v


def _fit(field: ContactField, points: np.ndarray, motions: np.ndarray, inliers: float,
         iterations: int = 8) -> np.ndarray:
    """Gauss-Newton on (turn, shift) per motion, over the best-matching `inliers` share of
    the outline: a near symmetry need not turn about the centroid (the one feature moves
    the centroid off the rest's centre), and the feature must not pull the fit."""
    motions = motions.copy()
    for _ in range(iterations):
        u, v = _moved(points, motions)
        d, gu, gv = field.distance(u, v)
        use = np.abs(d) <= np.quantile(np.abs(d), inliers, axis=1, keepdims=True)
        # d(u, v)/d(turn) = (-(v - shift v), u - shift u)
        jt = gu * -(v - motions[:, 2:3]) + gv * (u - motions[:, 1:2])
        jac = np.stack([jt, gu, gv], axis=-1) * use[..., None]  # (A, P, 3)
        normal = np.einsum("apk,apl->akl", jac, jac) + 1e-12 * np.eye(3)
        rhs = np.einsum("apk,ap->ak", jac, d * use)
        step = np.linalg.solve(normal, rhs[..., None])[..., 0]
        motions -= np.clip(step, [-0.05, -0.002, -0.002], [0.05, 0.002, 0.002])
    return motions


def near_symmetries(field: ContactField, tolerance: float = 0.001, coverage: float = 0.6,
                    resolution: float = np.deg2rad(2.0), exclude: float = np.deg2rad(15.0)
                    ) -> np.ndarray:
    """Motions (A, 3) = (turn, shift u, shift v), best match first, under which at least
    `coverage` of the outline lands within `tolerance` metres of itself. Turns within
    `exclude` of none are not rivals. A round outline (most turns match) returns turns every
    5 degrees: its heading cannot be told at all. Kept while the field lives."""
    return kept(field, ("near symmetries", tolerance, coverage, resolution, exclude),
                lambda: _near_symmetries(field, tolerance, coverage, resolution, exclude))


def _near_symmetries(field: ContactField, tolerance: float, coverage: float,
                     resolution: float, exclude: float) -> np.ndarray:
    points, _ = field.contour.resampled(0.001)
    turns = np.arange(exclude, 2 * np.pi - exclude + 1e-9, resolution)
    coarse = np.column_stack([turns, np.zeros((len(turns), 2))])
    err = _mismatch(field, points, coarse, coverage)
    if np.mean(err <= tolerance) > 0.3:
        round_turns = np.arange(1, 72) * np.deg2rad(5.0)
        found = np.column_stack([round_turns, np.zeros((len(round_turns), 2))])
    else:
        left, right = np.roll(err, 1), np.roll(err, -1)
        left[0], right[-1] = np.inf, np.inf
        # a shifted match can hide behind a coarse mismatch of a few millimetres
        minima = np.flatnonzero((err <= left) & (err <= right) & (err <= 0.005))
        fitted = _fit(field, points, coarse[minima], inliers=0.5)
        fitted_err = _mismatch(field, points, fitted, coverage)
        keep = (fitted_err <= tolerance) & (np.abs(np.angle(np.exp(1j * fitted[:, 0])))
                                            >= exclude)
        found = fitted[keep][np.argsort(fitted_err[keep])]
        if len(found) > 1:  # two coarse minima that fitted onto one motion are one
            distinct = [0]
            for i in range(1, len(found)):
                if np.all(np.abs(np.angle(np.exp(1j * (found[i, 0] - found[distinct, 0]))))
                          > np.deg2rad(2.0)):
                    distinct.append(i)
            found = found[distinct]
    found = np.array(found, dtype=np.float64).reshape(-1, 3)
    found[:, 0] = (found[:, 0] + np.pi) % (2 * np.pi) - np.pi
    found.setflags(write=False)
    return found


def images(pose: np.ndarray, motions: np.ndarray) -> np.ndarray:
    """The poses (A, 3) that place the object where `pose` (3,) places it, up to each
    near symmetry m: pose o m, which reads the same wherever the outline matches."""
    if len(motions) == 0:
        return np.empty((0, 3))
    c, s = np.cos(pose[2]), np.sin(pose[2])
    x = pose[0] + c * motions[:, 1] - s * motions[:, 2]
    z = pose[1] + s * motions[:, 1] + c * motions[:, 2]
    heading = (pose[2] + motions[:, 0] + np.pi) % (2 * np.pi) - np.pi
    return np.column_stack([x, z, heading])


NAMED_APART = np.deg2rad(5.0)
"""Turns closer than this are named once in a warning: a near symmetry's fit may land on
two motions a few degrees apart (a held-out triangle, one side 0.5 mm longer, was warned
of turns "116, 119, -119")."""


def named_turns(motions: np.ndarray) -> list[float]:
    """The distinct turns of `motions` (best match first), each named once: those within
    `NAMED_APART` of a better match are the same turn."""
    named: list[float] = []
    for turn in motions[:, 0]:
        if all(abs(np.angle(np.exp(1j * (turn - t)))) >= NAMED_APART for t in named):
            named.append(float(turn))
    return named


ROUND_CLOSER = 0.0005
"""Metres: an outline round within `near_symmetries`' millimetre is looked at again this
close, where a gear's teeth tell its turns apart from any turn (a held-out 12-tooth gear was
called "nearly round over most of it", with no word that it repeats every 30 degrees)."""
MANY = 12
"""More turns than this that map the outline onto itself: it is round, not repeating."""
EVEN = np.deg2rad(3.0)
"""How far from an even share of the full turn a fitted near symmetry may lie and still be
said as "every N degrees" (a gear's fits lay 0.6 degrees off)."""


def turns_text(motions: np.ndarray) -> str:
    """The turns of `motions` in words, each once: "every 30 degrees" for four or more
    multiples of one turn that go all the way round, else "under a turn of 119, -119
    degrees"."""
    turns = sorted(named_turns(motions), key=abs)
    spacing = 2 * np.pi / (len(turns) + 1)  # n turns and the identity, evenly round
    steps = np.mod(np.array(turns), 2 * np.pi) / spacing  # 1 .. n, if they are
    if (len(turns) >= 4 and np.all(np.abs(steps - np.round(steps)) * spacing < EVEN)
            and len(set(np.round(steps).astype(int))) == len(turns)):
        return f"every {np.degrees(spacing):.0f} degrees"
    return f"under a turn of {', '.join(f'{np.degrees(t):.0f}' for t in turns)} degrees"


def symmetry_warning(field: ContactField) -> str | None:
    """A warning for an outline that nearly repeats under turns (`near_symmetries`), as a
    map's check gives one: a held-out lab's 44 x 11 mm outline, its ends 15 % apart in
    thickness, got no word of its half turn, and one run declared the half-turned image."""
    motions = near_symmetries(field)
    if len(motions) == 0:
        return None
    if len(motions) > MANY:  # a D-shaped cam with a 33 mm flat too: its heading is told there
        closer = near_symmetries(field, tolerance=ROUND_CLOSER)
        repeats = (f"; within {ROUND_CLOSER * 1e3:g} mm it repeats {turns_text(closer)}"
                   if 0 < len(closer) <= MANY else "")
        return ("the outline is nearly round over most of it: most turns map all but a "
                "feature onto itself, so only where it departs from round (a flat, a notch, "
                f"a bump) tells the heading, and without one 'not yet' is the right "
                f"answer{repeats}")
    return (f"the outline nearly repeats {turns_text(motions)}: poses a turn "
            "relates differ only where a feature breaks the symmetry, or not at all ('not "
            "yet' is then the right answer)")
