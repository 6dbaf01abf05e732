"""What a map offers a fingertip, checked on load: units, slopes, features, plains, symmetries.

A map that is wrong in a way the localizer cannot see (heights in millimetres, a tip that
does not fit) should be named before an episode, not discovered from a baffling result.
`check_map` refuses what cannot work (`MapError`, via `surface.check_radius`) and warns
about what will work badly; `haptic map check` prints the whole report and `haptic run`
prints the warnings.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from service.localization.surface import ContactSurface, HeightMap, contact_surface

PLAIN_TOLERANCE = 0.02
"""A plain: the contact height varies by less than this share of a step (0.2 mm for 10 mm
steps, twice B2's reading noise) within one step of a point, so a step there reads nothing."""
FEATURE_TOLERANCE = 2e-4
"""Relief (metres) a feature needs to count as one: twice B2's reading noise."""
FEATURE_ASPECT = 0.25
"""A feature is at least this tall for its width; so on smooth ground the smallest
"feature" is about its sharpest radius of curvature."""
WINDOW_GROWTH = 1.2
"""Windows for the smallest feature grow by this factor (a sample each side at least).
Doubling judged a boss 3 mm high and 9 mm wide by a 17 mm window, which asks a 1-in-4
feature for 4.25 mm, and called a profile across it one with no bump at all (a held-out
check)."""
MAX_PLAUSIBLE_RELIEF = 1.0
"""Metres. Objects a fingertip explores are not taller than this."""
MAX_PLAUSIBLE_EXTENT = 5.0
"""Metres. Nor wider."""
MM_SLOPE = 20.0
"""Rise over run (87 degrees). Real surfaces are this steep only at walls, a thin share of
the area; heights in millimetres over metres make most of the ground this steep."""
MM_STEEP_SHARE = 0.25
DIFFER_SAMPLES = 10_000
"""Samples (at most, about) of the grid on which a symmetry's differences are measured."""


@dataclass(frozen=True)
class MapReport:
    """The check of one map for one fingertip and step (lengths in metres)."""

    name: str
    shape: tuple[int, int]
    spacing: float
    radius: float
    step: float
    height_range: tuple[float, float]
    steepest_slope: float
    """Largest rise over run between neighbouring samples."""
    typical_slope: float
    """Median rise over run where the surface is not flat."""
    steep_share: float
    """Share of the area steeper than MM_SLOPE."""
    smallest_feature: float | None
    """Width of the narrowest bump or pit with at least FEATURE_TOLERANCE of relief and
    FEATURE_ASPECT of its width (on smooth ground, about its sharpest radius of curvature)."""
    hidden_share: float
    """Share of the area the tip cannot reach within FEATURE_TOLERANCE (pits narrower than it)."""
    hidden_depth: float
    plains_share: float
    tilt: tuple[float, float]
    """Rise over run along x and y of the slope most of the map shares (`dominant_slope`),
    where plains lie on it (a part scanned on a tilted fixture); (0, 0) where none do (a
    level part, a dome)."""
    symmetries: np.ndarray = field(repr=False)
    """(S, 3) motions (quarter turns, dx, dy) that map the contact surface nearly onto
    itself."""
    symmetry_strengths: np.ndarray = field(repr=False)
    """(S, 2) how well each motion holds: correlation of the surface with its image, and
    the share of the map where the two overlap."""
    warnings: tuple[str, ...] = ()
    surface: ContactSurface | None = field(default=None, repr=False, compare=False)
    """The contact surface checked: what a report measures only when shown."""

    @functools.cached_property
    def aligned_symmetries(self) -> np.ndarray:
        """`symmetries` with each shift aligned at full resolution (`align_motions`), as the
        report shows them and measures their differences."""
        if self.surface is None:
            return self.symmetries
        return align_motions(self.surface, self.symmetries)

    @functools.cached_property
    def symmetry_differences(self) -> np.ndarray:
        """(S, 6) where each motion's image differs from the surface (`image_differences`),
        each motion aligned first. Measured only when the report is shown or written: a
        correlation cannot tell an exact symmetry from one a feature breaks."""
        if self.surface is None:
            return np.full((len(self.symmetries), 6), np.nan)
        return image_differences(self.surface, self.aligned_symmetries)

    @property
    def _rising(self) -> str:
        """Which way the map's overall tilt rises, in words."""
        if self.is_profile:
            return "rising along it" if self.tilt[0] > 0 else "falling along it"
        toward = np.degrees(np.arctan2(self.tilt[1], self.tilt[0]))
        return f"rising toward {toward:.0f} deg from its x axis"

    @property
    def is_profile(self) -> bool:
        return self.shape[0] == 1

    @property
    def extent(self) -> tuple[float, float]:
        return ((self.shape[1] - 1) * self.spacing, (self.shape[0] - 1) * self.spacing)

    def lines(self) -> list[str]:
        """The report as text, one fact per line, lengths in millimetres."""
        lo, hi = self.height_range
        x, y = self.extent
        size = (f"profile {x * 1e3:g} mm long, {self.shape[1]} samples" if self.is_profile
                else f"{x * 1e3:g} x {y * 1e3:g} mm, {self.shape[1]} x {self.shape[0]} samples")
        flat = hi - lo < FEATURE_TOLERANCE
        area = "its length" if self.is_profile else "the area"
        smooth = ("none (flat)" if flat else
                  "no bump or pit as steep as 1 in 4 for its width; its steep slopes are "
                  "steps or walls between levels" if self.steepest_slope > FEATURE_ASPECT
                  else "none as steep as 1 in 4 for its width: smooth, gently varying ground")
        feature = (smooth
                   if self.smallest_feature is None else
                   f"{self.smallest_feature * 1e3:.3g} mm across (a bump, a pit, or the "
                   "edge of one)"
                   + (f", narrower than the tip ({2 * self.radius * 1e3:g} mm across): it is "
                      f"felt only blurred" if self.smallest_feature < 2 * self.radius else ""))
        lines = [
            f"map        {self.name}: {size} at {self.spacing * 1e3:g} mm",
            f"heights    {lo * 1e3:.3f} .. {hi * 1e3:.3f} mm (relief {(hi - lo) * 1e3:.3f} mm)",
            f"slope      steepest {_degrees(self.steepest_slope)}, typical "
            f"{_degrees(self.typical_slope)} where not flat",
            f"features   smallest {feature}",
            f"hidden     {self.hidden_share:.1%} of {area} lies deeper than the "
            f"{self.radius * 1e3:g} mm tip reaches (by up to {self.hidden_depth * 1e3:.2f} mm)",
            f"plains     {self.plains_share:.1%} of {area}: a {self.step * 1e3:g} mm step "
            f"there reads under {PLAIN_TOLERANCE * self.step * 1e3:.3g} mm"
            + ("" if self.tilt == (0.0, 0.0) else
               " more than the map's overall tilt would "
               f"({np.degrees(np.arctan(np.hypot(*self.tilt))):.1f} deg, {self._rising}): "
               "there a step tells at most which way the slope runs"),
            "symmetries " + ("every motion (the map is flat: no reading tells one pose "
                             "from another)" if flat else describe_symmetries(
                self.aligned_symmetries, self.symmetry_strengths, self.is_profile,
                self.extent, self.symmetry_differences)),
        ]
        return lines + [f"warning    {w}" for w in self.warnings]

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name, "shape": list(self.shape), "spacing": self.spacing,
            "radius": self.radius, "step": self.step, "height_range": list(self.height_range),
            "steepest_slope": self.steepest_slope, "typical_slope": self.typical_slope,
            "steep_share": self.steep_share,
            "smallest_feature": self.smallest_feature, "hidden_share": self.hidden_share,
            "hidden_depth": self.hidden_depth, "plains_share": self.plains_share,
            "tilt": list(self.tilt),
            "symmetries": self.aligned_symmetries.tolist(),
            "symmetry_correlation": self.symmetry_strengths[:, 0].tolist(),
            "symmetry_overlap": self.symmetry_strengths[:, 1].tolist(),
            "symmetry_differ_share": _nil_for_nan(self.symmetry_differences[:, 0]),
            "symmetry_differ_by": _nil_for_nan(self.symmetry_differences[:, 1]),
            "symmetry_differ_at": [None if np.isnan(at).any() else at.reshape(2, 2).tolist()
                                   for at in self.symmetry_differences[:, 2:]],
            "warnings": list(self.warnings),
        }


def _degrees(slope: float) -> str:
    return f"{np.degrees(np.arctan(slope)):.1f} deg ({slope:.3g} rise/run)"


def describe_symmetries(motions: np.ndarray, strengths: np.ndarray,
                        is_profile: bool = False,
                        extent: tuple[float, float] | None = None,
                        differences: np.ndarray | None = None) -> str:
    """The motions found, the strongest three shown with how well each holds and, given
    their `differences` (`image_differences`), where the image differs; a surface of
    revolution named as one, with its axis and how far its turns differ at most."""
    if len(motions) == 0:
        return "none found"
    from service.localization.localizers.symmetry import revolution_centre

    if differences is None:
        differences = np.full((len(motions), 6), np.nan)
    axis = None if is_profile or extent is None else revolution_centre(motions, extent)
    if axis is not None:
        turns = differences[(motions[:, 0] != np.round(motions[:, 0]))
                            & np.isfinite(differences[:, :2]).all(axis=1)]
        return (f"every turn about ({axis[0] * 1e3:.0f}, {axis[1] * 1e3:.0f}) mm nearly maps "
                f"the contact surface onto itself ({len(motions)} motions, correlation "
                f"{float(np.min(strengths[:, 0])):.2f} at least"
                + ("" if len(turns) == 0 else
                   "; " + _turns_differing(turns[:, 0].max(), turns[:, 1].max()))
                + "): a surface of revolution, whose heading only a feature off its axis or "
                "the map's edges tell")
    shown = []
    for (k, dx, dy), (corr, overlap), differ in zip(motions[:3], strengths[:3],
                                                    differences[:3], strict=True):
        how = (f" (correlation {corr:.2f} over {overlap:.0%} of the map"
               + ("" if np.isnan(differ).any() else f"; {_differing(*differ)}") + ")")
        turn = ({0: "shift", 1: "quarter turn", 2: "reversal" if is_profile else "half turn",
                 3: "three-quarter turn"}[int(k) % 4] if k == round(k)
                else f"turn by {k * 90:.0f} deg")
        if is_profile:
            motion = (f"{turn} by {dx * 1e3:+.0f} mm" if k == 0 else
                      f"{turn} (then shift {dx * 1e3:+.0f} mm)")
        elif k == 0:
            motion = f"shift by ({dx * 1e3:+.0f}, {dy * 1e3:+.0f}) mm"
        elif abs(dx) < 5e-4 and abs(dy) < 5e-4:
            motion = turn
        else:
            motion = f"{turn} then shift ({dx * 1e3:+.0f}, {dy * 1e3:+.0f}) mm"
        shown.append(motion + how)
    more = f"; and {len(motions) - 3} more" if len(motions) > 3 else ""
    several = len(motions) > 1
    return (f"{len(motions)} motion{'s' if several else ''} nearly map{'' if several else 's'} "
            f"the contact surface onto itself: {'; '.join(shown)}{more}")


_WITHIN = f"within {FEATURE_TOLERANCE * 1e3:.1f} mm"


def _differing(share: float, largest: float, x: float, y: float, x_to: float, y_to: float
               ) -> str:
    """Where an image differs, in words."""
    if share == 0:
        return f"the same {_WITHIN} throughout"
    return (f"the same {_WITHIN} but over {_share(share)} of it, by up to "
            f"{largest * 1e3:.2f} mm, most between ({x * 1e3:.0f}, {y * 1e3:.0f}) and "
            f"({x_to * 1e3:.0f}, {y_to * 1e3:.0f}) mm")


def _turns_differing(share: float, largest: float) -> str:
    """How far the turns of a surface of revolution differ at most, in words."""
    if share == 0:
        return f"every turned copy the same {_WITHIN} throughout"
    return (f"turned copies not the same {_WITHIN} over {_share(share)} of the map at most, "
            f"by up to {largest * 1e3:.2f} mm")


def _share(share: float) -> str:
    return "under 0.1%" if share < 0.001 else f"{share:.1%}"


def _nil_for_nan(values: np.ndarray) -> list[float | None]:
    """JSON has no NaN: an unmeasured value is null."""
    return [None if np.isnan(v) else float(v) for v in values]


ALIGNED = 16
"""The strongest motions whose shift `align_motions` aligns (the report shows three; a
lattice has hundreds, each a dozen milliseconds to align)."""


def align_motions(surface: ContactSurface, motions: np.ndarray) -> np.ndarray:
    """`motions` (S, 3) with the shift of the strongest `ALIGNED` moved to where the image
    differs from the surface least (the mean absolute difference, the height offset taken
    out), within a few samples of where it was found, to a tenth of a sample. They are
    found on a grid coarsened to about 160 samples across: a map exactly the same under a
    half turn was shown turned "then shift (+0, -3) mm" and "the same within 0.2 mm but
    over 65.7 % of it, by up to 1.79 mm" (a held-out helper's 400 x 200 mm map)."""
    from service.localization.localizers.symmetry import moved

    m = surface.map
    out = np.array(motions, dtype=np.float64).reshape(-1, 3)
    if m.is_profile or len(out) == 0:
        return out
    rows, cols = m.heights.shape
    x, y = _sample_grid(m, DIFFER_SAMPLES // 4)
    keep = _inward(m, surface.radius, x, y)
    if not keep.any():  # a map narrower than the tip: no place to compare (a held-out
        return out  # 12 mm strip printed numpy's "Mean of empty slice" around its report)
    x, y = x[keep], y[keep]
    here, _ = surface.lookup(x, y)

    def misfit(motion: np.ndarray) -> float:
        mx, my = moved(m.extent, np.repeat(motion[np.newaxis], len(x), axis=0), x, y)
        both = _inward(m, surface.radius, mx, my)
        if np.count_nonzero(both) < 0.1 * len(x):
            return np.inf
        there, _ = surface.lookup(mx[both], my[both])
        d = there - here[both]
        return float(np.mean(np.abs(d - np.median(d))))

    coarse = m.spacing * int(np.ceil(max(rows, cols) / 160))  # `symmetry._find`'s grid
    if coarse <= m.spacing:
        return out  # found at full resolution
    around = np.array([(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1) if i or j], float)
    for motion in out[:ALIGNED]:
        found, best, step = motion.copy(), misfit(motion), coarse
        while step >= 0.1 * m.spacing:
            tries = [t for t in (motion + np.array([0.0, i * step, j * step])
                                 for i, j in around)
                     if np.all(np.abs(t[1:] - found[1:]) <= coarse)]  # its grid's reach
            fits = [misfit(t) for t in tries]
            k = int(np.argmin(fits)) if fits else 0
            if fits and fits[k] < best:
                motion[:], best = tries[k], fits[k]
            else:
                step /= 2
    return out


def image_differences(surface: ContactSurface, motions: np.ndarray) -> np.ndarray:
    """(S, 6) for each motion (quarter turns, dx, dy): the share of the map where the
    contact surface and its image differ by more than FEATURE_TOLERANCE, the height offset
    a reading cannot tell taken out; the largest difference (metres); and the two places
    it compares there (x, y and the point the motion takes it to, metres): a feature at
    one of them breaks the symmetry (which, one motion cannot tell). An exact symmetry
    differs nowhere; one that a feature breaks differs there only (a chamfered corner of
    a plate, four alike holes); a square boss turned by 45 degrees differs at its corners.
    Measured on a grid of about `DIFFER_SAMPLES` samples, a tip's radius in from the map's
    edges, where a surface seen through a tip is cut short; NaN where a motion's image
    leaves no sample to compare."""
    from service.localization.localizers.symmetry import moved

    m = surface.map
    x, y = _sample_grid(m, DIFFER_SAMPLES)
    inward = _inward(m, surface.radius, x, y)
    here, _ = surface.lookup(x, y)
    out = np.full((len(motions), 6), np.nan)
    for i, motion in enumerate(motions):
        mx, my = moved(m.extent, np.repeat(motion[np.newaxis, :3], len(x), axis=0), x, y)
        there, _ = surface.lookup(mx, my)
        both = np.flatnonzero(inward & _inward(m, surface.radius, mx, my))
        if len(both) == 0:
            continue
        d = np.abs((there - here)[both] - np.median((there - here)[both]))
        most = both[int(np.argmax(d))]
        out[i] = (np.count_nonzero(d > FEATURE_TOLERANCE) / np.count_nonzero(inward),
                  float(d.max()), x[most], y[most], mx[most], my[most])
    return out


def _sample_grid(m: HeightMap, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of about `samples` map samples on a regular stride, flattened."""
    rows, cols = m.heights.shape
    stride = max(1, int(np.ceil(np.sqrt(rows * cols / samples))))
    x, y = np.meshgrid(np.arange(0, cols, stride) * m.spacing,
                       np.arange(0, rows, stride) * m.spacing)
    return x.ravel(), y.ravel()


def _inward(m: HeightMap, margin: float, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Mask of the points (x, y) at least `margin` inside the map (along it, on a profile)."""
    x_max, y_max = m.extent
    inside = (x >= margin - 1e-12) & (x <= x_max - margin + 1e-12)
    if not m.is_profile:
        inside &= (y >= margin - 1e-12) & (y <= y_max - margin + 1e-12)
    return inside


def check_map(height_map: HeightMap, radius: float, step: float = 0.01) -> MapReport:
    """Check `height_map` for a tip of `radius` moving in steps of `step` (metres).

    Raises MapError when the tip cannot be used on the map at all.
    """
    surface = contact_surface(height_map, radius)  # refuses a radius the map cannot take
    z, h = height_map.heights, height_map.spacing
    slopes = _slopes(z, h)
    flat = slopes < FEATURE_TOLERANCE / max(step, h)
    typical = float(np.median(slopes[~flat])) if np.any(~flat) else 0.0
    hidden = hidden_depths(surface)
    report = dict(
        name=height_map.name, shape=height_map.shape, spacing=h, radius=float(radius),
        step=float(step), height_range=(float(z.min()), float(z.max())),
        steepest_slope=float(slopes.max()), typical_slope=typical,
        steep_share=float(np.mean(slopes > MM_SLOPE)),
        smallest_feature=_smallest_feature(z, h, int(max(step, 2 * radius) / h) + 1),
        hidden_share=float(np.mean(hidden > FEATURE_TOLERANCE)),
        hidden_depth=float(hidden.max()),
        **_plains(surface, step),
        **_symmetries(surface),
    )
    return MapReport(**report, warnings=tuple(_warnings(MapReport(**report))),
                     surface=surface)


def _slopes(z: np.ndarray, h: float) -> np.ndarray:
    """Rise over run at each sample, toward the next sample along each axis: the slope of
    the plane through the three (a 5-degree plane rising at 45 degrees to the axes was
    3.5 degrees along either)."""
    along_x = np.zeros_like(z)
    along_x[:, :-1] = np.diff(z, axis=1) / h
    along_y = np.zeros_like(z)
    if z.shape[0] > 1:
        along_y[:-1, :] = np.diff(z, axis=0) / h
    return np.hypot(along_x, along_y)


def hidden_depths(surface: ContactSurface) -> np.ndarray:
    """How far below the lowest point the tip reaches each sample lies: the contact surface
    eroded by the same sphere (a morphological closing) minus the map."""
    from service.localization.surface import sphere_filter

    traced = sphere_filter(surface.centre_heights, surface.radius, surface.map.spacing,
                           erode=True)
    return np.maximum(traced - surface.map.heights, 0.0)


def _smallest_feature(z: np.ndarray, h: float, widest: int) -> float | None:
    """The narrowest window (samples, odd, growing by about `WINDOW_GROWTH`) whose grey
    opening or closing removes a bump or pit tall enough to count (FEATURE_TOLERANCE,
    FEATURE_ASPECT)."""
    width = 3
    while width <= max(widest, 3) * 4 and width <= max(z.shape):
        size = (1, width) if z.shape[0] == 1 else (width, width)
        bumps = z - ndimage.grey_opening(z, size=size, mode="nearest")
        pits = ndimage.grey_closing(z, size=size, mode="nearest") - z
        if max(bumps.max(), pits.max()) > max(FEATURE_TOLERANCE, FEATURE_ASPECT * width * h):
            return (width - 1) * h
        width = max(width + 2, 2 * round(WINDOW_GROWTH * width / 2) + 1)
    return None


def _plains(surface: ContactSurface, step: float) -> dict[str, Any]:
    """The report's `plains_share` and `tilt`: the level plains, and those on the slope
    most of the map shares where there are any (a share of the map of 1 % or more)."""
    level = _even(surface, step, (0.0, 0.0))
    tilt = dominant_slope(surface)
    if tilt != (0.0, 0.0):
        sloped = level | _even(surface, step, tilt)
        if np.mean(sloped) - np.mean(level) >= 0.01:
            return {"plains_share": float(np.mean(sloped)), "tilt": tilt}
    return {"plains_share": float(np.mean(level)), "tilt": (0.0, 0.0)}


def plains(surface: ContactSurface, step: float, tilt: tuple[float, float] = (0.0, 0.0)
           ) -> np.ndarray:
    """Mask of the points where the contact height varies by less than PLAIN_TOLERANCE of a
    step within a step's reach (a square window), level or beyond an even slope of `tilt`
    (rise over run along x and y): a step on an even slope reads that slope wherever it
    is, which tells where the finger is no better than a level plain does (a plate
    scanned 3 degrees off level was 0 % plain, the same plate level 88 %)."""
    level = _even(surface, step, (0.0, 0.0))
    return level if tilt == (0.0, 0.0) else level | _even(surface, step, tilt)


def _even(surface: ContactSurface, step: float, tilt: tuple[float, float]) -> np.ndarray:
    """Mask of the points within a step's reach of which the contact height departs from an
    even slope of `tilt` by less than PLAIN_TOLERANCE of a step. A step shorter than half
    a sample is judged over one sample, at that sample's share (its window was the point
    alone, and every map "100 % plain" at `--step 0.0005` on 1 mm)."""
    k = max(1, int(round(step / surface.map.spacing)))
    reach = max(step, k * surface.map.spacing)
    size = (1, 2 * k + 1) if surface.map.is_profile else (2 * k + 1, 2 * k + 1)
    c = surface.centre_heights
    if tilt != (0.0, 0.0):
        rows, cols = c.shape
        h = surface.map.spacing
        c = c - (tilt[0] * h * np.arange(cols)[np.newaxis, :]
                 + tilt[1] * h * np.arange(rows)[:, np.newaxis])
    return _span(c, size) < PLAIN_TOLERANCE * reach


def _span(c: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Highest minus lowest of `c` within a window of `size` about each point."""
    return (ndimage.maximum_filter(c, size=size, mode="nearest")
            - ndimage.minimum_filter(c, size=size, mode="nearest"))


def dominant_slope(surface: ContactSurface) -> tuple[float, float]:
    """Rise over run along x and y that most of the contact surface shares: the median of
    its slope between neighbouring samples (a level plate's plains make it zero, whatever
    its features; a tilted scan's, the tilt)."""
    c, h = surface.centre_heights, surface.map.spacing
    along_x = float(np.median(np.diff(c, axis=1))) / h if c.shape[1] > 1 else 0.0
    along_y = float(np.median(np.diff(c, axis=0))) / h if c.shape[0] > 1 else 0.0
    return along_x, along_y



def _symmetries(surface: ContactSurface) -> dict[str, np.ndarray]:
    """The report's `symmetries` and `symmetry_strengths`."""
    if surface.map.is_profile:
        found = profile_symmetry_matches(surface.centre_heights[0], surface.map.spacing)
    else:
        from service.localization.localizers.symmetry import symmetry_matches

        found = symmetry_matches(surface, relative=True)  # heights read from the start
    strengths = np.minimum(found[:, 3:], 1.0)  # a correlation, not its rounding error past 1
    return {"symmetries": found[:, :3], "symmetry_strengths": strengths}


def profile_symmetries(row: np.ndarray, spacing: float, threshold: float = 0.97,
                       min_overlap: float = 0.3) -> np.ndarray:
    """(S, 3) motions of a profile onto itself: shifts (k = 0) and reversals (k = 2, the
    finger facing the other way), by normalized correlation over at least `min_overlap`."""
    return profile_symmetry_matches(row, spacing, threshold, min_overlap)[:, :3]


def profile_symmetry_matches(row: np.ndarray, spacing: float, threshold: float = 0.97,
                             min_overlap: float = 0.3) -> np.ndarray:
    """(S, 5) `profile_symmetries` with each one's correlation and overlap share. A profile
    flatter than `FEATURE_TOLERANCE` has none, as a flat map has none (`symmetry._masked_ncc`):
    its rounding error correlated with itself at every shift, and a flat profile 20 mm up
    listed 1,961 motions where a flat map listed none (a held-out check)."""
    from service.localization.localizers.symmetry import FEATURED

    if np.ptp(row) < FEATURE_TOLERANCE:
        return np.empty((0, 5))
    a = row - row.mean()
    n = len(a)
    found = []
    for k, other in ((0, a), (2, a[::-1])):
        num = np.correlate(a, other, mode="full")
        lags = np.arange(-(n - 1), n)
        overlap = n - np.abs(lags)
        # a[i + lag] pairs with other[i]: a's window and other's window for each lag, each
        # about its own mean (heights are read relative to the start: `symmetry._masked_ncc`)
        a_lo, a_hi = np.maximum(lags, 0), np.minimum(n + lags, n)
        b_lo, b_hi = np.maximum(-lags, 0), np.minimum(n - lags, n)
        s_a, s_b = _window_sums(a, a_lo, a_hi), _window_sums(other, b_lo, b_hi)
        varied_a = _window_sums(a * a, a_lo, a_hi) - s_a ** 2 / overlap
        varied_b = _window_sums(other * other, b_lo, b_hi) - s_b ** 2 / overlap
        ncc = (num - s_a * s_b / overlap) / np.sqrt(np.maximum(varied_a * varied_b, 1e-300))
        # a stretch of plain correlates with any other at random: both copies must vary
        total = FEATURED * overlap / n * np.sum(a * a)
        ncc[(varied_a < total) | (varied_b < total)] = -1.0
        ok = (overlap >= min_overlap * n) & (ncc >= threshold)
        ok &= ncc == ndimage.maximum_filter1d(ncc, 5)
        if k == 0:
            ok &= lags != 0
        for lag in lags[ok]:
            found.append((k, -lag * spacing, 0.0, ncc[lag + n - 1], overlap[lag + n - 1] / n))
    found.sort(key=lambda f: -f[3])
    return np.array(found, dtype=np.float64).reshape(-1, 5)


def _window_sums(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Sums of x[lo:hi] for each pair of bounds."""
    cumulative = np.concatenate([[0.0], np.cumsum(x)])
    return cumulative[hi] - cumulative[lo]


def _warnings(r: MapReport) -> list[str]:
    lo, hi = r.height_range
    relief, (x, y) = hi - lo, r.extent
    size = f"{x:.4g} m profile" if r.is_profile else f"{x:.4g} x {y:.4g} m map"
    warnings = []
    if relief > MAX_PLAUSIBLE_RELIEF or relief > max(x, y) or r.steep_share > MM_STEEP_SHARE:
        # in millimetres the relief would still outspan the map: micrometres (a scan's
        # integer heights were told "divide them by 1000")
        unit, factor = (("micrometres", "1,000,000") if relief / 1000 > max(x, y)
                        else ("millimetres", "1000"))
        warnings.append(
            f"heights span {relief:.4g} m over a {size}, {r.steep_share:.0%} "
            f"of it steeper than 87 deg: they look like {unit}; heights must be in metres "
            f"(divide them by {factor})")
    if max(x, y) > MAX_PLAUSIBLE_EXTENT:
        warnings.append(f"the map spans {size.removesuffix(' map')}: is --spacing in millimetres? "
                        f"It is in metres ({r.spacing:g} mm would be {r.spacing / 1000:g})")
    if r.radius < 2 * r.spacing:
        warnings.append(f"the tip's radius ({r.radius * 1e3:g} mm) spans under two samples "
                        f"({r.spacing * 1e3:g} mm apart): its contact model is coarse; use a "
                        "finer map")
    shorter = x if r.is_profile else min(x, y)
    if 2 * r.radius > shorter:
        warnings.append(f"the tip ({2 * r.radius * 1e3:g} mm across) is wider than the map "
                        f"({shorter * 1e3:g} mm): every contact height depends on ground "
                        "beyond its edges, which it takes to continue the edge's heights; "
                        "give a wider map or a smaller tip")
    starts = x if r.is_profile else min(x, y)
    if starts <= 4 * r.step:  # as `scenario.check_start` refuses a run with noise
        warnings.append(f"the map ({starts * 1e3:g} mm across) is too small for a step of "
                        f"{r.step * 1e3:g} mm: `haptic run --noise` draws starts two steps "
                        "inside every edge, which leaves none; use a smaller --step")
    if r.step < r.spacing:
        warnings.append(f"a step ({r.step * 1e3:g} mm) is shorter than the sample spacing "
                        f"({r.spacing * 1e3:g} mm)")
    if r.plains_share > 0.8:
        warnings.append(f"{r.plains_share:.0%} of the map is plain: the finger must travel to a "
                        "feature before it can localize; expect many steps")
    if len(r.symmetries):
        warnings.append(f"the surface nearly repeats under {len(r.symmetries)} motion(s) (see "
                        "symmetries): poses they relate differ only where a feature breaks "
                        "the symmetry, or not at all ('not yet' is then the right answer)")
    return warnings
