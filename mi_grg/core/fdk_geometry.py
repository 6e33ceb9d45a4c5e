"""What FDK needs of a scan beyond a centred circle: offset-detector (half-fan) and
short-scan redundancy weights, each view's own source-detector frame, and where FDK is not
meaningful.

Offset detector (Wang 2002, in the form of RTK's DisplacedDetectorImageFilter): with
``l`` the column's detector coordinate (offsets included) and ``theta`` the half-width of
the part of the detector centred on the principal ray, the weight is 0 beyond ``-theta``
on the short side, 2 beyond ``theta`` on the long side and
``1 + sin(pi/2 atan(l / DSD) / atan(theta / DSD))`` between, so that opposite rays of a
full circle add up to 2 (FDK's full-scan factor 1/2 stays). The short side is then
zero-padded by one detector width so that the ramp-filtered values there are
back-projected too. A shift below a tenth of the width is not weighted (as RTK). A
per-view scan weighs each view with its own distances and principal point, ``theta`` the
narrowest overlap of its views at the axis (as RTK).

Short scan (Parker 1982, in the form of RTK's ParkerShortScanImageFilter): cone-beam views
over less than a full circle, the largest gap between neighbouring views being a gap (see
``GAP_STEPS``, ``GAP_DEG``). With ``beta`` the view's angle from the first view after that
gap, ``2 delta`` the arc beyond pi up to the last view, and ``alpha = atan(-l / DSO)`` the
column's fan angle (``l`` its coordinate scaled to the axis, offsets included), the weight
rises as ``2 sin^2(pi beta / (4 (delta - alpha)))`` up to ``beta = 2 (delta - alpha)``,
is 2 up to ``pi - 2 alpha`` and falls as ``2 sin^2(pi (pi + 2 delta - beta) / (4 (delta +
alpha)))`` to ``pi + 2 delta``, so that the two rays of a line add up to 2 again. Each view
then counts with its own angular step (half the arc to its two neighbours, as RTK's
angular gaps) instead of the full circle's 2 pi / n. Parker's weights need ``delta`` of at
least half the fan angle (pi plus the fan angle of data); ``caveats`` says when it is less.
A per-view scan's views take their own gantry angle (the source's azimuth), distance and
principal point here, as RTK's do. A full circle keeps 2 pi / n per view where RTK takes
each view's step: the steps measured no better on circles with views left out
(docs/per_view_geometry.md).

Per-view frames (RTK's FDK for its 3-D circular geometry does the same): each view's
source-to-detector distance ``DSD_i`` (to the detector plane, along its normal), its
source-to-axis distance ``DSO_i`` and principal point (foot of the normal from the source)
set the cosine weight, the ramp's sample spacing and the back-projection's magnification
and distance weight; the voxel is projected onto the view's own detector plane.
"""
from __future__ import annotations

import numpy as np

from mi_grg.core.geometry import Geometry

__all__ = ["offset_weights", "pad_offset_detector", "short_scan", "short_scan_weights",
           "view_angles", "view_fdk_frames", "view_steps", "caveats"]

# RTK's rule: shifts below this fraction of the width need no redundancy weights
MIN_SHIFT = 0.1
# per-view deviations from the nominal circle beyond which FDK is only approximate
MAX_TILT_DEG = 5.0          # detector roll / tilt
MAX_HEIGHT = 0.05           # source height, fraction of DSO
MAX_DISTANCE = 0.1          # DSO, DSD relative change
# a full circle may lack a few views (held-out ones): a gap counts beyond both of these
GAP_STEPS, GAP_DEG = 2.5, 45.0


def _corners(geo: Geometry):
    nu = geo.nDetector[1]
    du = geo.dDetector[1]
    inf = (0.5 - nu / 2) * du + geo.offDetector[1]
    sup = (nu / 2 - 0.5) * du + geo.offDetector[1]
    return inf, sup


def offset_weights(geo: Geometry):
    """The redundancy weights of the columns, float64 [1, nu] (a circular scan) or [view,
    nu] (a per-view cone-beam scan: each view's own distances and principal point, the
    overlap the narrowest of the views', as RTK's), or None (centred enough)."""
    inf, sup = _corners(geo)
    if abs(inf + sup) < MIN_SHIFT * abs(sup - inf):
        return None
    if inf > 0 or sup < 0:
        return None      # the principal ray misses the detector: ``caveats`` says so
    if geo.per_view and geo.mode == "cone":
        l, dsd, dso = _view_columns(geo, view_angles(geo))    # on each view's detector
        iso = l * dso / dsd                                   # the same, at the axis
        theta = min(-float(iso.min(1).max()), float(iso.max(1).min()))
        ramp = np.arctan(l / dsd) / np.arctan(theta / dso)
    else:
        l = _columns(geo)[None, :]
        theta = min(-inf, sup)
        sdd = geo.DSD if geo.mode == "cone" else None
        ramp = (np.arctan(l / sdd) / np.arctan(theta / sdd)) if sdd else l / theta
    w = 1.0 + np.sin(0.5 * np.pi * np.clip(ramp, -1.0, 1.0))
    return w if sup + inf > 0 else 2.0 - w


def _columns(geo: Geometry) -> np.ndarray:
    """Each column's centre on the detector along u, offsets included [nu] (float64)."""
    nu = geo.nDetector[1]
    return (np.arange(nu) + 0.5 - nu / 2) * geo.dDetector[1] + geo.offDetector[1]


def view_angles(geo: Geometry) -> np.ndarray:
    """Each view's gantry angle (radians) [view], float64: a per-view cone-beam scan's
    from its source's azimuth (as RTK takes each view's own gantry angle), otherwise the
    nominal ``geo.angles``."""
    if not (geo.per_view and geo.mode == "cone"):
        return np.asarray(geo.angles, np.float64)
    src = geo.view_vectors()[:, 0:3]
    return np.arctan2(src[:, 1], src[:, 0])


def _view_columns(geo: Geometry, angles):
    """(each column's centre along the orbit's tangent (-sin a, cos a, 0) from the view's
    principal point [view, nu], DSD [view, 1], DSO [view, 1]), float64; the nominal
    ``_columns`` [1, nu], DSD and DSO on a circular scan."""
    if not geo.per_view:
        return _columns(geo)[None, :], geo.DSD, geo.DSO
    f = view_fdk_frames(geo)
    vec = f["vectors"]
    nu = geo.nDetector[1]
    tangent = np.stack([-np.sin(angles), np.cos(angles), np.zeros_like(angles)], 1)
    j = np.arange(nu) + 0.5 - nu / 2
    first = np.sum((vec[:, 3:6] - f["foot"]) * tangent, 1)
    l = first[:, None] + j[None, :] * np.sum(vec[:, 6:9] * tangent, 1)[:, None]
    return l, f["dsd"][:, None], f["dso"][:, None]


def view_steps(angles) -> np.ndarray:
    """Each view's angular step (half the arc to its two neighbours, RTK's angular gaps)
    over the full circle's 2 pi / n [view], float64."""
    s, order, gaps = _gaps(angles)
    step = np.empty(s.size)
    step[order] = 0.5 * (gaps + np.roll(gaps, 1))
    return step * s.size / (2 * np.pi)


def _gaps(angles):
    """(angles mod 2 pi sorted, the order, each sorted angle's gap to the next, wrapping)."""
    a = np.mod(np.asarray(angles, np.float64), 2 * np.pi)
    order = np.argsort(a, kind="stable")
    s = a[order]
    return s, order, np.diff(np.concatenate([s, s[:1] + 2 * np.pi]))


def _is_gap(gap: float, n_views: int) -> bool:
    """Whether a gap between neighbouring views breaks the circle (``GAP_STEPS``,
    ``GAP_DEG``): a full circle may lack a few held-out views."""
    return n_views > 1 and gap > max(GAP_STEPS * 2 * np.pi / n_views, np.radians(GAP_DEG))


def short_scan(geo: Geometry):
    """``(first, delta)`` of a cone-beam short scan: the angle (mod 2 pi) of the first view
    after the largest gap and half the arc beyond pi that the views span; None for a full
    circle (no gap counts: ``GAP_STEPS``, ``GAP_DEG``) or a parallel-beam scan."""
    if geo.mode != "cone" or geo.n_views < 2:
        return None
    s, _, gaps = _gaps(view_angles(geo))
    k = int(np.argmax(gaps))
    if not _is_gap(gaps[k], s.size):
        return None
    first = s[(k + 1) % s.size]
    span = 2 * np.pi - gaps[k]                 # from the first view to the last
    return float(first), float(0.5 * (span - np.pi))


def _half_fan_angle(geo: Geometry) -> float:
    """The larger of the fan angles to the detector's two side edges (radians): Parker's
    weights need delta beyond it."""
    inf, sup = _corners(geo)
    du = geo.dDetector[1]
    return float(np.arctan(max(abs(inf - 0.5 * du), abs(sup + 0.5 * du)) / geo.DSD))


def short_scan_weights(geo: Geometry):
    """Parker's weights times each view's angular step over the full circle's, float64
    [view, nu] (module docstring), or None for a full circle. A per-view scan's views
    take their own gantry angle (``view_angles``), distance and principal point."""
    scan = short_scan(geo)
    if scan is None:
        return None
    first, delta = scan
    angles = view_angles(geo)
    l, dsd, _ = _view_columns(geo, angles)
    alpha = np.arctan(-l / dsd)                              # atan(-l / DSO_i), l at the axis
    beta = np.mod(angles - first, 2 * np.pi)[:, None]
    tiny = 1e-12                                # delta -/+ alpha <= 0: no data to weight
    rise = 2 * np.sin(np.pi * beta / (4 * np.maximum(delta - alpha, tiny))) ** 2
    fall = 2 * np.sin(np.pi * (np.pi + 2 * delta - beta)
                      / (4 * np.maximum(delta + alpha, tiny))) ** 2
    w = np.where(beta <= 2 * delta - 2 * alpha, rise,
                 np.where(beta <= np.pi - 2 * alpha, 2.0,
                          np.where(beta <= np.pi + 2 * delta, fall, 0.0)))
    return w * view_steps(angles)[:, None]


def pad_offset_detector(proj: np.ndarray, geo: Geometry):
    """(weighted projections zero-padded by one width on the short side, the geometry of
    the padded detector), or the inputs unchanged for a centred detector."""
    w = offset_weights(geo)
    if w is None:
        return proj, geo
    nv, nu = geo.nDetector
    long_plus = sum(_corners(geo)) > 0
    out = np.zeros((proj.shape[0], nv, 2 * nu), np.float32)
    cols = slice(nu, 2 * nu) if long_plus else slice(0, nu)
    out[:, :, cols] = proj * w[:, None, :].astype(np.float32)
    du = geo.dDetector[1]
    shift = -nu / 2 * du if long_plus else nu / 2 * du    # the padded detector's centre
    padded = geo.replace(nDetector=(nv, 2 * nu), sDetector=(geo.sDetector[0], 2 * nu * du),
                         offDetector=(geo.offDetector[0], geo.offDetector[1] + shift))
    if geo.per_view:
        vec = np.array(geo.vectors)
        vec[:, 3:6] += shift / du * vec[:, 6:9]
        padded = padded.replace(vectors=vec)
    return out, padded


def view_fdk_frames(geo: Geometry) -> dict:
    """Per-view FDK frame, float64 [view] / [view, 3]: ``dsd``, ``dso``, the principal
    point ``foot`` (where the normal through the source meets the detector plane;
    parallel beam: the ray through the axis), unit ``n`` (source towards detector), and
    the rows of ``view_vectors``."""
    vec = geo.view_vectors()
    s, d, U, V = vec[:, 0:3], vec[:, 3:6], vec[:, 6:9], vec[:, 9:12]
    eu = U / np.linalg.norm(U, axis=1, keepdims=True)
    ev = V / np.linalg.norm(V, axis=1, keepdims=True)
    n = np.cross(eu, ev)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    if geo.mode == "cone":
        n *= np.sign(np.sum((d - s) * n, 1))[:, None]
        dsd = np.sum((d - s) * n, 1)
        dso = -np.sum(s * n, 1)
        foot = s + dsd[:, None] * n
    else:
        n *= np.sign(np.sum(s * n, 1))[:, None]
        dsd = dso = np.full(len(vec), np.inf)
        foot = d - np.sum(d * n, 1)[:, None] * n      # where the ray through the axis meets
    return {"dsd": dsd, "dso": dso, "foot": foot, "n": n, "vectors": vec}


def dual_steps(U, V):
    """Rows iu, iv [view, 3] with iu . U = iv . V = 1 and iu . V = iv . U = 0 in the
    detector plane: the column and row offsets of a plane offset h are h . iu, h . iv,
    also where U and V are not at right angles (U / |U|^2, V / |V|^2 where they are)."""
    uu, vv, uv = (np.sum(x * y, 1, keepdims=True) for x, y in ((U, U), (V, V), (U, V)))
    if not np.any(uv):
        return U / uu, V / vv
    det = uu * vv - uv * uv
    return (vv * U - uv * V) / det, (uu * V - uv * U) / det


def _elevation_deg(a) -> float:
    """The largest angle of the unit rows ``a`` out of the z = 0 plane (degrees)."""
    return float(np.degrees(np.arcsin(np.clip(np.abs(a[:, 2]), 0, 1))).max())


def caveats(geo: Geometry) -> list:
    """Why FDK is only approximate on this scan (empty: FDK is meaningful)."""
    out = []
    inf, sup = _corners(geo)
    if inf > 0 or sup < 0:
        out.append("the detector does not cover the principal ray (offset beyond half its "
                   "width)")
    gap = float(_gaps(view_angles(geo))[2].max())
    offset = offset_weights(geo) is not None
    short = short_scan(geo)
    if short is not None and offset:
        out.append(f"the views leave a gap of {np.degrees(gap):.0f} degrees with an "
                   "offset detector (no weights here for a short half-fan scan)")
    elif short is not None and short[1] < _half_fan_angle(geo):
        out.append(f"the short scan spans {180 + 2 * np.degrees(short[1]):.0f} degrees, less "
                   f"than 180 plus the fan angle ({180 + 2 * np.degrees(_half_fan_angle(geo)):.0f})")
    elif short is None and offset and _is_gap(gap, geo.n_views):
        out.append(f"the views leave a gap of {np.degrees(gap):.0f} degrees (a "
                   "half-fan scan needs a full circle)")
    if geo.per_view and geo.mode == "cone":
        f = view_fdk_frames(geo)
        vec = f["vectors"]
        eu = vec[:, 6:9] / np.linalg.norm(vec[:, 6:9], axis=1, keepdims=True)
        roll, tilt = _elevation_deg(eu), _elevation_deg(f["n"])
        height = float(np.abs(vec[:, 2]).max()) / geo.DSO
        dist = max(float(np.abs(f["dso"] / geo.DSO - 1).max()),
                   float(np.abs(f["dsd"] / geo.DSD - 1).max()))
        if max(roll, tilt) > MAX_TILT_DEG:
            out.append(f"a detector is rolled or tilted by {max(roll, tilt):.1f} degrees "
                       f"(> {MAX_TILT_DEG})")
        if height > MAX_HEIGHT:
            out.append(f"the source leaves the orbit plane by {height:.0%} of DSO "
                       f"(> {MAX_HEIGHT:.0%})")
        if dist > MAX_DISTANCE:
            out.append(f"the source / detector distances vary by {dist:.0%} (> {MAX_DISTANCE:.0%})")
    return out
