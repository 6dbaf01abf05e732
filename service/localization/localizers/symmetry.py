"""Symmetries of a surface: rigid motions that map the contact surface onto itself.

On a periodic surface (an egg-crate) every image of the true pose under such a motion reads
the same heights, so no amount of exploring away from the edges can tell them apart. A
bounded pool may never have sampled some of those images; this module finds the motions
once per surface (normalized cross-correlation of the surface with itself turned through
0, 90, 180 and 270 degrees, and through other turns where the surface nearly repeats under
them, by FFT) so a localizer can test the images of its leading pose explicitly before it
declares anything.

A motion g(q) = rho^k(q + delta) is stored as (k, delta_x, delta_y): rho turns the map a
quarter turn about its centre, and k need not be whole (a hexagonal lattice: k = 2/3).
"""

from __future__ import annotations

import numpy as np
from scipy import fft, ndimage

from service.localization.memo import kept
from service.localization.surface import ContactSurface

OTHER_TURN_STEP = 2.0
"""Degrees between the turns tried that are not quarter turns (`_other_turns`)."""
LATTICE = (0.8, 0.5)
"""A turn also counts where the surface correlates with it at the first (below the near
symmetry's bar) and with every turn between it and the nearest quarter turns under the
second: a lattice (a 60-degree knurl correlates with its 60-degree turn at 0.83, and with
its 30-degree turn at 0.03), where a smooth shell or terrain correlates with any turn at
0.5-0.9 over some shift."""
LATTICE_TURN = 0.7
"""`LATTICE`'s first bar for turns other than quarter turns: over the whole map a 12 mm
diamond knurl correlates with its 60-degree turn at 0.75 only (its worn patch and the
map's corners), and a pose 60 degrees off was declared."""
OTHER_TURN_SIDE = 100
"""Samples along the map's side at which those turns are tried (a coarse map is plenty to
find a pattern's turn, and each turn costs a correlation)."""

def symmetries(surface: ContactSurface, threshold: float = 0.85, min_overlap: float = 0.3,
               limit: int = 400) -> np.ndarray:
    """(S, 3) motions (quarter turns k, dx, dy in metres) under which the surface repeats,
    nearly: a symmetric pattern that one feature breaks (four holes and a chamfered
    corner) correlates with its quarter turns at 0.9, not 0.97, and a localizer must test
    those images until a reading has touched the feature. A false symmetry costs only a
    few image poses that fit worse; a missed one declared quarter turns
    (pattern:20:1, seed 4)."""
    return symmetry_matches(surface, threshold, min_overlap, limit)[:, :3]


def symmetry_matches(surface: ContactSurface, threshold: float = 0.85,
                     min_overlap: float = 0.3, limit: int = 400, relative: bool = False
                     ) -> np.ndarray:
    """(S, 5) `symmetries` with how well each holds: the correlation of the surface with
    its image, and the share of the map where the two overlap. A report must give both:
    a plate whose pocket is a rectangle correlates with its half turn at 0.9 over a third
    of the map, though its bosses do not repeat. Kept while the surface lives.

    `relative` correlates the two copies each about its own mean where they overlap, as a
    finger reads heights (relative to its start): it also finds a copy that lies a constant
    height above the other (a staircase's treads alike). The map check reports those; a
    localizer tests the images of the motions found without it, as its whole-map
    certificate stands for the rest: with them, on `haptic bench objects --families
    shell,terrain` 93 of 120 runs localized instead of 96, and none declared wrong either
    way (BENCHMARKS.md, twenty-second session). Both lists come of one search (the same
    transforms), kept together: `haptic run` asks for both, and found each on its own at
    first (twice the search: the localizer's list after the map check's took 0.34 and
    0.48 s more on `peaks` in two throwaway timings, 0 s now)."""
    return kept(surface, ("symmetries", threshold, min_overlap, limit),
                lambda: _find(surface, threshold, min_overlap, limit))[relative]


KINDS = (False, True)
"""The correlations every search finds at once: absolute (about the map's mean), relative
(each copy about its own mean over the overlap: `symmetry_matches`)."""


def _find(surface: ContactSurface, threshold: float, min_overlap: float, limit: int
          ) -> dict[bool, np.ndarray]:
    """Each kind's (S, 5) motions (`KINDS`)."""
    a = surface.centre_heights
    if surface.map.is_profile or min(a.shape) < 8:
        return {relative: np.empty((0, 5)) for relative in KINDS}
    step = max(1, int(np.ceil(max(a.shape) / 160)))  # coarse is plenty to find a period
    a = a[::step, ::step]
    a = a - a.mean()
    h = surface.map.spacing * step
    turns = (0, 1, 2, 3) if a.shape[0] == a.shape[1] else (0, 2)
    ones = np.ones_like(a)
    found: dict[bool, list] = {relative: [] for relative in KINDS}
    for k in turns:
        nccs, overlap = _masked_ncc(a, np.rot90(a, k), ones, min_overlap)
        for relative, ncc in nccs.items():
            peaks = ((ncc >= min(threshold, LATTICE[0]))
                     & (ncc == ndimage.maximum_filter(ncc, size=5)))
            u, v = np.nonzero(peaks)
            shift_y, shift_x = u - (a.shape[0] - 1), v - (a.shape[1] - 1)
            if k == 0:  # the identity is no rival
                keep = (shift_x != 0) | (shift_y != 0)
                u, v, shift_x, shift_y = u[keep], v[keep], shift_x[keep], shift_y[keep]
            found[relative] += [(k, -shift_x[i] * h, -shift_y[i] * h, ncc[u[i], v[i]],
                                 overlap[u[i], v[i]] / a.size) for i in range(len(u))]
    # other turns keep a share of the room: a lattice's shifts and half turns alone
    # correlate better and would fill it; a surface of revolution keeps every turn. (On
    # a long rectangle a turned copy overlaps too little to tell a turn from chance.)
    others = (_other_turns(surface.centre_heights, surface.map.spacing, surface.map.extent,
                           threshold, min_overlap) if a.shape[0] == a.shape[1]
              else {relative: [] for relative in KINDS})
    return {relative: _ranked(found[relative], others[relative], limit)
            for relative in KINDS}


def _ranked(found: list, others: list, limit: int) -> np.ndarray:
    """At most `limit` motions, best first: quarter turns and shifts (`found`) beside the
    other turns (`others`), which keep a share of the room."""
    found = sorted(found, key=lambda f: -f[3])
    # the most overlap first: their images land on the map, near the truth's
    others = _each_turn_a_share(sorted(others, key=lambda f: -f[3] * f[4]),
                                max(limit // 4, len({round(f[0] * 90.0) for f in others})))
    found = sorted(found[:limit - len(others)] + others, key=lambda f: -f[3])
    return np.array(found[:limit], dtype=np.float64).reshape(-1, 5)


def _each_turn_a_share(found: list, room: int) -> list:
    """Up to `room` of `found` (best first), taken from each turn in turn: one turn's many
    shifts must not crowd out another turn's."""
    by_turn: dict[float, list] = {}
    for f in found:
        by_turn.setdefault(round(f[0] * 90.0), []).append(f)
    queues = list(by_turn.values())
    kept = []
    for rank in range(max((len(q) for q in queues), default=0)):
        kept += [q[rank] for q in queues if rank < len(q)]
    return kept[:room]


def _other_turns(a: np.ndarray, h: float, extent: tuple[float, float], threshold: float,
                 min_overlap: float) -> dict[bool, list[tuple[float, float, float, float, float]]]:
    """Near symmetries under turns that are not quarter turns (a hexagonal grid of bumps
    under 60 degrees, a gear under its teeth's pitch), as motions with a fractional count
    of quarter turns. Each turn of `OTHER_TURN_STEP` degrees is tried; one counts where the
    best correlation over every shift peaks above `threshold`, and falls below it
    between this turn and the nearest quarter turns (a smooth surface correlates with itself
    turned a little, a shoulder of the identity, not a symmetry), or peaks above
    `LATTICE`'s first where it falls below its second between them. A turn that counts is
    refined to a tenth of a degree and its shifts to a fraction of a sample, so its images
    land within a polish of the poses they stand for. A held-out check of ours found 7
    wrong declarations in 5,000 runs on such surfaces, each the truth turned so. Each kind
    of correlation (`KINDS`) has its own list, of one set of turned copies."""
    coarse = max(1, int(np.ceil(max(a.shape) / OTHER_TURN_SIDE)))
    # samples spread evenly about the map's centre, which the turns are about (`images`)
    first = ((a.shape[0] - 1) % coarse) // 2
    a = a[first::coarse, first::coarse][:(a.shape[0] - 1 - first) // coarse + 1,
                                        :(a.shape[1] - 1 - first) // coarse + 1]
    a = a - a.mean()
    h = h * coarse
    angles = np.arange(0.0, 360.0, OTHER_TURN_STEP)
    # a quarter turn: found exactly, a wall between peaks
    tried = np.array([deg % 90.0 != 0.0 for deg in angles])
    best = {relative: np.ones(len(angles)) for relative in KINDS}
    peak: dict[bool, dict[int, tuple[float, float, float, float, float]]] = {
        relative: {} for relative in KINDS}
    for i in np.flatnonzero(tried):
        nccs, overlap = _turned_ncc(a, angles[i], min_overlap)
        for relative, ncc in nccs.items():
            u, v = np.unravel_index(int(np.argmax(ncc)), ncc.shape)
            best[relative][i] = ncc[u, v]
            peak[relative][i] = _motion(ncc, overlap, u, v, angles[i], a.shape, h)
    return {relative: _turns_that_count(a, h, extent, threshold, min_overlap, angles, tried,
                                        best[relative], peak[relative], relative)
            for relative in KINDS}


def _turns_that_count(a: np.ndarray, h: float, extent: tuple[float, float],
                      threshold: float, min_overlap: float, angles: np.ndarray,
                      tried: np.ndarray, best: np.ndarray,
                      peak: dict[int, tuple[float, float, float, float, float]],
                      relative: bool) -> list[tuple[float, float, float, float, float]]:
    """`_other_turns` of one kind, from each coarse turn's `best` correlation and its
    `peak` motion; a turn that counts refined on `a`, the coarse map."""
    if np.all(best[tried] >= threshold):
        # the surface repeats under every turn, each about one centre: a surface of
        # revolution (a turned part, rings, a bowl), whose truth lies at any turn of a pose
        # about it; a turn every `OTHER_TURN_STEP` degrees about the axis. (Each turn's
        # best shift alone may be a ring's pitch off: rings alike but for the innermost.)
        motions = [peak[i] for i in np.flatnonzero(tried)]
        axis = np.median([_fixed_point(m[0], m[1], m[2], extent) for m in motions], axis=0)
        return [(k, *_about(axis, k, extent), corr, share) for k, _, _, corr, share in motions]
    found = []
    n = len(angles)
    for i, deg in enumerate(angles):
        if not tried[i] or best[i] < min(threshold, LATTICE_TURN) \
                or best[i] < max(best[(i - 1) % n], best[(i + 1) % n]):
            continue  # not a peak over the turn
        # below the bar on the way to the nearest quarter turn, either side
        left = next(j for j in range(1, n) if angles[(i - j) % n] % 90.0 == 0.0)
        right = next(j for j in range(1, n) if angles[(i + j) % n] % 90.0 == 0.0)
        dips = max(min(best[(i - j) % n] for j in range(1, left)) if left > 1 else 1.0,
                   min(best[(i + j) % n] for j in range(1, right)) if right > 1 else 1.0)
        bar = LATTICE_TURN if dips < LATTICE[1] else threshold if dips < threshold else None
        if bar is None:
            continue
        fine = deg + np.arange(-1.0, 1.01, 0.1) * OTHER_TURN_STEP / 2
        turns = [_turned_ncc(a, d, min_overlap) for d in fine]
        k = int(np.argmax([t[0][relative].max() for t in turns]))
        ncc, overlap = turns[k][0][relative], turns[k][1]
        peaks = (ncc >= bar) & (ncc == ndimage.maximum_filter(ncc, size=5))
        found += [_motion(ncc, overlap, u, v, fine[k], a.shape, h)
                  for u, v in zip(*np.nonzero(peaks), strict=True)]
    return found


def _motion(ncc: np.ndarray, overlap: np.ndarray, u: int, v: int, deg: float,
            shape: tuple[int, ...], h: float) -> tuple[float, float, float, float, float]:
    """The motion (quarter turns, dx, dy, correlation, overlap share) of the peak at sample
    (u, v) of the correlation with the surface turned by `deg`, its shift refined to a
    fraction of a sample."""
    dy, dx = _subsample(ncc, u, v)
    return (deg / 90.0, -(v + dx - (shape[1] - 1)) * h, -(u + dy - (shape[0] - 1)) * h,
            float(ncc[u, v]), float(overlap[u, v]) / (shape[0] * shape[1]))


def _turned_ncc(a: np.ndarray, deg: float, min_overlap: float
                ) -> tuple[dict[bool, np.ndarray], np.ndarray]:
    """Normalized correlation of `a` with itself turned by `deg` degrees (about its centre)
    at every shift, -1 where they overlap on less than `min_overlap` of it; and the
    overlaps, in samples."""
    mask = (ndimage.rotate(np.ones_like(a), deg, reshape=False, order=1) > 0.999
            ).astype(np.float64)
    return _masked_ncc(a, mask * ndimage.rotate(a, deg, reshape=False, order=1), mask,
                       min_overlap)


FEATURED = 0.02
"""An overlap counts only where each copy varies over it by at least this share of what
the map varies over a region of its size (`_masked_ncc`): a plain does not vary at all,
while part of a dome varies far less than the whole dome does (at 0.1 two shells lost a
symmetry; at this share every preset keeps every one it had)."""


def _masked_ncc(a: np.ndarray, b: np.ndarray, mask: np.ndarray, min_overlap: float
                ) -> tuple[dict[bool, np.ndarray], np.ndarray]:
    """Normalized correlation of `a` (mean zero) with `b` (zero off `mask`, where it is
    defined) at every shift, of each kind (`KINDS`), -1 where they overlap on less than
    `min_overlap` of `a` or where either varies too little over the overlap (`FEATURED`);
    and the overlaps, in samples. Two plains correlate perfectly: on a plate with one hole,
    turned copies that missed the hole named the wrong axis of revolution, and a flat map
    "every turn about" an arbitrary point."""
    shape = [2 * n - 1 for n in a.shape]
    padded = [fft.next_fast_len(n, real=True) for n in shape]

    def spectrum(x: np.ndarray) -> np.ndarray:
        return fft.rfft2(x, padded)

    def back(spectrum: np.ndarray) -> np.ndarray:
        return fft.irfft2(spectrum, padded)[:shape[0], :shape[1]]

    # each array transformed once: the six sums below are products of their spectra
    f_a, f_aa, f_ones = spectrum(a), spectrum(a * a), spectrum(np.ones_like(a))
    f_mask, f_b, f_bb = (spectrum(x[::-1, ::-1]) for x in (mask, b, b * b))
    overlap, ss_a, ss_b = back(f_ones * f_mask), back(f_aa * f_mask), back(f_ones * f_bb)
    n = np.maximum(overlap, 1.0)
    sum_a, sum_b = back(f_a * f_mask), back(f_ones * f_b)
    varied_a, varied_b = ss_a - sum_a ** 2 / n, ss_b - sum_b ** 2 / n
    product = back(f_a * f_b)
    nccs = {False: product / np.sqrt(np.maximum(ss_a * ss_b, 1e-300)),
            True: (product - sum_a * sum_b / n) / np.sqrt(  # each about its own mean
                np.maximum(varied_a * varied_b, 1e-300))}
    featured = ((varied_a >= FEATURED * n / a.size * np.sum(a * a))
                & (varied_b >= FEATURED * n / max(mask.sum(), 1.0) * np.sum(b * b))
                & (varied_a > 0) & (varied_b > 0))
    for ncc in nccs.values():
        ncc[(overlap < min_overlap * a.size) | ~featured] = -1.0
    return nccs, overlap


def _subsample(ncc: np.ndarray, u: int, v: int) -> tuple[float, float]:
    """Where a peak at sample (u, v) lies between samples: a parabola through it and its
    neighbours along each axis."""
    def offset(lo: float, mid: float, hi: float) -> float:
        curve = lo - 2 * mid + hi
        return float(np.clip(0.5 * (lo - hi) / curve, -0.5, 0.5)) if curve < 0 else 0.0
    rows, cols = ncc.shape
    dy = offset(ncc[u - 1, v], ncc[u, v], ncc[u + 1, v]) if 0 < u < rows - 1 else 0.0
    dx = offset(ncc[u, v - 1], ncc[u, v], ncc[u, v + 1]) if 0 < v < cols - 1 else 0.0
    return dy, dx


def _convolve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The full 2-D linear convolution by FFT: `scipy.signal.fftconvolve(a, b)`, whose
    module imports scipy.stats and cost every compute process 1.5 s at start."""
    shape = [a.shape[i] + b.shape[i] - 1 for i in range(2)]
    padded = [fft.next_fast_len(n, real=True) for n in shape]
    out = fft.irfft2(fft.rfft2(a, padded) * fft.rfft2(b, padded), padded)
    return out[:shape[0], :shape[1]]


REVOLUTION_TURNS = 90
"""Distinct turns (other than quarter turns) that make a surface of revolution: every turn
tried, `OTHER_TURN_STEP` degrees apart, counts on one (`_other_turns`)."""


def revolution_centre(motions: np.ndarray, extent: tuple[float, float]
                      ) -> tuple[float, float] | None:
    """Where a surface of revolution's axis lies (metres), or None if `motions` are not
    those of one: the fixed point of its turns (`_other_turns` makes them all turns about
    it)."""
    other = motions[motions[:, 0] != np.round(motions[:, 0])]
    if len(np.unique(np.round(other[:, 0] * 90.0))) < REVOLUTION_TURNS:
        return None
    x, y = np.median([_fixed_point(k, dx, dy, extent) for k, dx, dy in other[:, :3]], axis=0)
    return float(x), float(y)


def _fixed_point(k: float, dx: float, dy: float, extent: tuple[float, float]) -> np.ndarray:
    """The point a turn by `k` quarter turns then shift (`images`: q -> m + R(q + delta - m),
    m the map's centre) leaves where it is: m + (I - R)^-1 R delta."""
    turn = _turn(k)
    return np.array(extent) / 2 + np.linalg.solve(np.eye(2) - turn, turn @ np.array([dx, dy]))


def _about(axis: np.ndarray, k: float, extent: tuple[float, float]) -> tuple[float, float]:
    """The shift delta of the motion that turns by `k` quarter turns about `axis`:
    R^-1 (c - m) - (c - m), c the axis, m the map's centre."""
    arm = axis - np.array(extent) / 2
    dx, dy = _turn(k).T @ arm - arm
    return float(dx), float(dy)


def _turn(k: float) -> np.ndarray:
    c, s = np.cos(k * np.pi / 2), np.sin(k * np.pi / 2)
    return np.array([[c, -s], [s, c]])


def images(surface: ContactSurface, pose: np.ndarray, motions: np.ndarray) -> np.ndarray:
    """The start poses that the motions make of `pose` (3,) and that start on the map:
    they read the same heights as `pose` wherever their paths stay on it."""
    if len(motions) == 0:
        return np.empty((0, 3))
    x, y = moved(surface.map.extent, motions, np.full(len(motions), float(pose[0])),
                 np.full(len(motions), float(pose[1])))
    heading = pose[2] + motions[:, 0] * (np.pi / 2)
    return np.column_stack([x, y, heading])[surface.map.inside(x, y)]


def moved(extent: tuple[float, float], motions: np.ndarray, x: np.ndarray, y: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray]:
    """Where each motion (M, 3) takes its point (x[i], y[i]) of the map: shifted by (dx,
    dy), then turned by its quarter turns about the map's centre. A pose's image
    (`images`) reads the same heights at the points its readings are moved to. On a
    rectangle only half turns are taken (`_find` offers no other quarter turn there)."""
    x_max, y_max = extent
    x = x + motions[:, 1]
    y = y + motions[:, 2]
    quarter = motions[:, 0] == np.round(motions[:, 0])
    for turn in range(1, 4):  # rho: (x, y) -> (L - y, x) on a square map
        mask = quarter & (motions[:, 0] >= turn)
        if extent[0] == extent[1]:
            x[mask], y[mask] = x_max - y[mask], x[mask].copy()
        elif turn == 2:  # a half turn on a rectangle: (x, y) -> (X - x, Y - y)
            x[mask], y[mask] = x_max - x[mask], y_max - y[mask]
    other = ~quarter  # any other turn: about the map's centre, as rho is
    if np.any(other):
        turn = motions[other, 0] * (np.pi / 2)
        u, v = x[other] - x_max / 2, y[other] - y_max / 2
        x[other] = x_max / 2 + np.cos(turn) * u - np.sin(turn) * v
        y[other] = y_max / 2 + np.sin(turn) * u + np.cos(turn) * v
    return x, y
