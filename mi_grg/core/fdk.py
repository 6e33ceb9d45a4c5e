"""FDK (cone beam) and FBP (parallel beam) reconstruction in Dr.Jit.

Steps (Feldkamp, Davis & Kress 1984; Kak & Slaney ch. 3; weights as in TIGRE):

1. Cosine pre-weighting (cone only): p * DSO / sqrt(DSO^2 + u^2 + v^2), with the pixel's
   detector coordinates (u, v) scaled to the iso-centre (x DSO / DSD).
2. Ramp filter along u, row by row: the band-limited ramp is built in the *spatial* domain
   (h[0] = 1/4, h[odd n] = -1/(pi n)^2, h[even n] = 0, Kak & Slaney eq. 61) and then
   Fourier transformed, which keeps the correct DC term (a frequency-sampled |w| would set
   it to 0 and shift the image by a constant); optional apodisation window; zero-padding
   to >= 2x the row length (power of two, >= 64) against circular wrap-around.
3. Voxel-driven back-projection: for every voxel and view the voxel centre is projected
   onto the detector, the filtered projection is sampled bilinearly (zero outside) and
   weighted by (DSO / (DSO - s))^2, s = the voxel's coordinate along the source direction
   (cone only). All views are fused in one kernel (a loop over views per voxel).
4. Scale by pi / n_views (= the angular step 2 pi / n of a full circle times the 1/2 of
   full-scan redundancy; also right for parallel beam over pi or 2 pi), so the output is
   in the density units of the ground truth (a short scan: each view's own angular step,
   ``mi_grg.core.fdk_geometry.short_scan_weights``).

Assumes equally spaced angles over a full circle (cone) or a half/full circle (parallel);
cone-beam short scans get Parker's weights and each view its own angular step, offset
detectors (half-fan) redundancy weights, per-view scans each view's own frame in the weights and
the back-projection (``mi_grg.core.fdk_geometry``); ``fdk`` says on stderr where FDK is
only approximate (``fdk_geometry.caveats``).
"""
from __future__ import annotations

import sys

import numpy as np

import drjit as dr
import mitsuba as mi

from mi_grg.core import fdk_geometry
from mi_grg.core.geometry import Geometry
from mi_grg.core.joseph import check_angles, check_projections

FILTERS = ("ram-lak", "shepp-logan", "cosine", "hann")


def _filter_length(n_u: int) -> int:
    """Zero-padded FFT length: a power of two >= max(64, 2 n_u)."""
    return max(64, 1 << int(np.ceil(np.log2(2 * n_u))))


def ramp_filter(n_u: int, window: str = "ram-lak") -> np.ndarray:
    """Frequency response (float64, length ``_filter_length(n_u)``) of the band-limited
    ramp for unit sample spacing, times the apodisation ``window``.

    The response is the DFT of the spatial kernel, so it equals the discrete convolution
    with h[n] = 1/4 (n = 0), -1/(pi n)^2 (n odd), 0 (n even != 0)."""
    if window not in FILTERS:
        raise ValueError(f"filter must be one of {FILTERS}, got {window!r}")
    L = _filter_length(n_u)
    n = np.arange(L)
    n = np.where(n < L // 2, n, n - L)         # circular, centred at index 0
    h = np.zeros(L)
    h[0] = 0.25
    odd = (n % 2) != 0
    h[odd] = -1.0 / (np.pi * n[odd]) ** 2
    H = np.real(np.fft.fft(h))                 # even kernel -> real response
    f = np.abs(np.fft.fftfreq(L))              # cycles per sample, in [0, 0.5]
    if window == "shepp-logan":
        H *= np.sinc(f)                        # sin(pi f) / (pi f)
    elif window == "cosine":
        H *= np.cos(np.pi * f)
    elif window == "hann":
        H *= 0.5 * (1.0 + np.cos(2.0 * np.pi * f))
    return H


def filter_projections(proj: np.ndarray, geometry: Geometry, filter: str = "ram-lak"
                       ) -> np.ndarray:
    """Weighted and ramp-filtered projections [view, v, u] (float32), ready for
    ``fdk_backproject``; includes the pi / n_views angular factor."""
    geo = geometry
    nv, nu = geo.nDetector
    dv, du = geo.dDetector
    n_views = proj.shape[0]
    p = proj.astype(np.float64)
    if geo.per_view and geo.mode == "cone":
        p, tau = _view_weights(p, geo)
    elif geo.mode == "cone":
        mag = geo.DSO / geo.DSD                # detector -> iso-centre scaling
        u = ((np.arange(nu) + 0.5 - nu / 2) * du + geo.offDetector[1]) * mag
        v = ((np.arange(nv) + 0.5 - nv / 2) * dv + geo.offDetector[0]) * mag
        p = p * (geo.DSO / np.sqrt(geo.DSO ** 2 + u[None, :] ** 2 + v[:, None] ** 2))
        tau = du * mag                         # sample spacing at the iso-centre
    else:
        tau = du
    H = ramp_filter(nu, filter)
    L = H.size
    spec = np.fft.rfft(p, n=L, axis=-1) * H[: L // 2 + 1]
    q = np.fft.irfft(spec, n=L, axis=-1)[..., :nu]
    # Q = tau * sum h_phys p with h_phys = h / tau^2; times the angular factor pi / n
    q *= (1.0 / tau) * (np.pi / n_views)
    return q.astype(np.float32)


def _view_weights(p, geo: Geometry):
    """Cosine weights and ramp spacing [view, 1, 1] of a per-view cone-beam scan, from each
    view's own distances and principal point (``fdk_geometry.view_fdk_frames``)."""
    f = fdk_geometry.view_fdk_frames(geo)
    nv, nu = geo.nDetector
    vec = f["vectors"]
    U, V = vec[:, 6:9], vec[:, 9:12]
    # the pixel's squared distance from the principal point, |a U + b V - rel|^2 with
    # rel = foot - centre: written with dot products, so sheared rows are measured right
    rel = f["foot"] - vec[:, 3:6]
    a = (np.arange(nu) + 0.5 - nu / 2)[None, None, :]
    b = (np.arange(nv) + 0.5 - nv / 2)[None, :, None]
    col = lambda x: x[:, None, None]  # noqa: E731
    dot = lambda x, y: col(np.sum(x * y, 1))  # noqa: E731
    r2 = (a * a * dot(U, U) + 2 * a * b * dot(U, V) + b * b * dot(V, V)
          - 2 * a * dot(U, rel) - 2 * b * dot(V, rel) + dot(rel, rel))
    dsd = col(f["dsd"])
    p = p * (dsd / np.sqrt(dsd ** 2 + np.maximum(r2, 0.0)))
    du = col(np.linalg.norm(U, axis=1))
    return p, du * col(f["dso"] / f["dsd"])


def _magnification(s, cone, DSD, DSO):
    """Detector magnification and FDK distance weight (DSO / (DSO - s))^2 (cone); 1, 1
    for parallel beam."""
    if not cone:
        return 1.0, 1.0
    r = 1.0 / (DSO - s)
    return DSD * r, dr.square(DSO * r)


def _bilinear(q, offset, cu, cv, nu: int, nv: int):
    """Bilinear sample of the view starting at flat index ``offset`` of ``q`` at continuous
    pixel indices (cu, cv) (pixel centres at integers; zero outside the detector)."""
    Float, UInt, Int = mi.Float, mi.UInt32, mi.Int32
    fu, fv = dr.floor(cu), dr.floor(cv)
    iu, iv = Int(fu), Int(fv)
    wu1, wv1 = cu - fu, cv - fv
    wu0, wv0 = 1.0 - wu1, 1.0 - wv1
    mu0 = (iu >= 0) & (iu < nu)
    mu1 = (iu >= -1) & (iu < nu - 1)
    mv0 = (iv >= 0) & (iv < nv)
    mv1 = (iv >= -1) & (iv < nv - 1)
    base = Int(offset) + iv * nu + iu
    return (wv0 * (wu0 * dr.gather(Float, q, UInt(base), mv0 & mu0)
                   + wu1 * dr.gather(Float, q, UInt(base + 1), mv0 & mu1))
            + wv1 * (wu0 * dr.gather(Float, q, UInt(base + nu), mv1 & mu0)
                     + wu1 * dr.gather(Float, q, UInt(base + nu + 1), mv1 & mu1)))


@dr.syntax
def _backproject_kernel(q, cos_t, sin_t, geo: Geometry, n_views):
    """Voxel-driven, distance-weighted back-projection of flat filtered projections ``q``
    [view, v, u]; returns the flat volume [x, y, z] (mi.Float)."""
    Float, UInt, Int = mi.Float, mi.UInt32, mi.Int32
    nx, ny, nz = geo.nVoxel
    nv, nu = geo.nDetector
    dv, du = geo.dDetector
    ax = [np.float32(a[0]) for a in geo.voxel_axes()]   # first voxel centre per axis
    dvx, dvy, dvz = geo.dVoxel
    idx = dr.arange(UInt, nx * ny * nz)
    ix, iy, iz = idx // (ny * nz), (idx // nz) % ny, idx % nz
    x = dr.fma(Float(ix), dvx, ax[0])
    y = dr.fma(Float(iy), dvy, ax[1])
    z = dr.fma(Float(iz), dvz, ax[2])
    cone = geo.mode == "cone"
    DSD, DSO = geo.DSD, geo.DSO
    # detector coordinate -> continuous pixel index with pixel centres at integers
    cu0 = nu / 2 - 0.5 - geo.offDetector[1] / du
    cv0 = nv / 2 - 0.5 - geo.offDetector[0] / dv
    acc = dr.zeros(Float, nx * ny * nz)
    k = UInt(0)
    n_pix = nv * nu
    while k < n_views:
        ca = dr.gather(Float, cos_t, k)
        sa = dr.gather(Float, sin_t, k)
        s = x * ca + y * sa                    # along the source direction
        t = y * ca - x * sa                    # along e_u
        m, wgt = _magnification(s, cone, DSD, DSO)
        cu = dr.fma(t * m, 1.0 / du, cu0)
        cv = dr.fma(-z * m, 1.0 / dv, cv0)     # e_v = -z
        acc += wgt * _bilinear(q, k * n_pix, cu, cv, nu, nv)
        k += 1
    return acc


def fdk_backproject(q: np.ndarray, geometry: Geometry, angles=None) -> "mi.Float":
    """Distance-weighted voxel-driven back-projection of filtered projections ``q``
    [view, v, u] -> flat mi.Float volume [x, y, z] (no further scaling)."""
    a = check_angles(angles, geometry)
    if geometry.per_view:
        geo = geometry.with_angles(a)
        tables = [mi.Float(c.astype(np.float32)) for c in _bp_tables(geo)]
        out = _backproject_vectors_kernel(
            mi.Float(np.ascontiguousarray(q, np.float32).reshape(-1)), tables, geo,
            dr.opaque(mi.UInt32, a.size))
        dr.eval(out)
        return out
    cos_t = mi.Float(np.cos(a).astype(np.float32))
    sin_t = mi.Float(np.sin(a).astype(np.float32))
    out = _backproject_kernel(mi.Float(np.ascontiguousarray(q, np.float32).reshape(-1)),
                              cos_t, sin_t, geometry, dr.opaque(mi.UInt32, a.size))
    dr.eval(out)
    return out


def _bp_tables(geo: Geometry) -> list:
    """Per-view back-projection constants [view] (float64): source (parallel: 0), unit
    normal n (source towards detector), detector centre, the dual steps of u and v (a
    plane offset dotted with them gives its column and row offsets), DSO_i."""
    f = fdk_geometry.view_fdk_frames(geo)
    vec = f["vectors"]
    src = vec[:, 0:3] if geo.mode == "cone" else np.zeros((len(vec), 3))
    iu, iv = fdk_geometry.dual_steps(vec[:, 6:9], vec[:, 9:12])
    dso = f["dso"] if geo.mode == "cone" else np.ones(len(vec))
    cols = [src, f["n"], vec[:, 3:6], iu, iv]
    return [c[:, k] for c in cols for k in range(3)] + [dso]


@dr.syntax
def _backproject_vectors_kernel(q, tables, geo: Geometry, n_views):
    """``_backproject_kernel`` for per-view frames: each voxel is projected from the
    view's source onto its own detector plane (parallel beam: along n), weighted by
    (DSO_i / depth)^2 (cone)."""
    Float, UInt, Int = mi.Float, mi.UInt32, mi.Int32
    nx, ny, nz = geo.nVoxel
    nv, nu = geo.nDetector
    ax = [np.float32(a[0]) for a in geo.voxel_axes()]
    dvx, dvy, dvz = geo.dVoxel
    idx = dr.arange(UInt, nx * ny * nz)
    ix, iy, iz = idx // (ny * nz), (idx // nz) % ny, idx % nz
    x = [dr.fma(Float(ix), dvx, ax[0]), dr.fma(Float(iy), dvy, ax[1]),
         dr.fma(Float(iz), dvz, ax[2])]
    cone = geo.mode == "cone"
    acc = dr.zeros(Float, nx * ny * nz)
    k = UInt(0)
    n_pix = nv * nu
    while k < n_views:
        t = [dr.gather(Float, c, k) for c in tables]
        rel = [x[i] - t[i] for i in range(3)]
        depth = rel[0] * t[3] + rel[1] * t[4] + rel[2] * t[5]
        if cone:
            # hit = s + m (x - s), m = ((d - s) . n) / depth
            m = ((t[6] - t[0]) * t[3] + (t[7] - t[1]) * t[4] + (t[8] - t[2]) * t[5]) / depth
            hit = [t[i] + m * rel[i] for i in range(3)]
            wgt = dr.square(t[15] / depth)
        else:
            off = (t[6] - x[0]) * t[3] + (t[7] - x[1]) * t[4] + (t[8] - x[2]) * t[5]
            hit = [x[i] + off * t[3 + i] for i in range(3)]
            wgt = 1.0
        h = [hit[i] - t[6 + i] for i in range(3)]
        cu = h[0] * t[9] + h[1] * t[10] + h[2] * t[11] + (nu / 2 - 0.5)
        cv = h[0] * t[12] + h[1] * t[13] + h[2] * t[14] + (nv / 2 - 0.5)
        acc += wgt * _bilinear(q, k * n_pix, cu, cv, nu, nv)
        k += 1
    return acc


def fdk_dr(proj, geometry: Geometry, angles=None, filter: str = "ram-lak") -> "mi.TensorXf":
    """FDK (cone) / FBP (parallel) as ``mi.TensorXf`` [x, y, z] (density, 1/length);
    short scans and offset detectors get redundancy weights
    (``fdk_geometry.short_scan_weights``, ``fdk_geometry.pad_offset_detector``)."""
    a = check_angles(angles, geometry)
    p = check_projections(proj, geometry, a)
    geo = geometry if angles is None else geometry.with_angles(a)
    w = fdk_geometry.short_scan_weights(geo)
    if w is not None:
        p = (p * w[:, None, :]).astype(np.float32)
    p, geo = fdk_geometry.pad_offset_detector(p, geo)
    q = filter_projections(p, geo, filter)
    return mi.TensorXf(fdk_backproject(q, geo), shape=tuple(geometry.nVoxel))


def fdk(proj, geometry: Geometry, angles=None, filter: str = "ram-lak") -> np.ndarray:
    """FDK (cone beam) or FBP (parallel beam) reconstruction.

    Args:
        proj: line integrals [view, v, u] = (len(angles), *nDetector), density x length.
        geometry: the scan; ``angles`` (radians) overrides ``geometry.angles``.
        filter: apodisation of the ramp: "ram-lak" (none), "shepp-logan", "cosine",
            "hann".
    Returns:
        float32 [x, y, z] densities in the units of the ground truth.
    """
    geo = geometry if angles is None else geometry.with_angles(check_angles(angles, geometry))
    reasons = fdk_geometry.caveats(geo)
    if reasons:
        print(f"fdk: not meaningful on this scan, the result is approximate: "
              f"{'; '.join(reasons)} (iterative methods, or init=pdhg for gr / r2, do not "
              "rely on FDK)", file=sys.stderr)
    return np.array(fdk_dr(proj, geometry, angles, filter).numpy(), copy=True)
