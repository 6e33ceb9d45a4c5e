"""Path-traced cross-check of the projector: Mitsuba's ``volpath`` vs exp(-projection).

An X-ray projection is -log of the transmittance T = exp(-integral of sigma along the ray).
Mitsuba's ``volpath`` estimates T without any line integral: delta tracking through a
purely absorbing medium (albedo 0) lit by a ``constant`` emitter of radiance 1 (= I0),
each sample is 1 (the path escaped) or 0 (absorbed), so the per-pixel estimate is a
Bernoulli mean with standard error sqrt(T (1 - T) / spp). Two routes:

* ``gaussian``: the medium is ``gaussian_medium`` (the Gaussians summed directly at every
  lookup, no voxelisation); reference: exp(-projection) of the closed-form projector
  (``mi_grg.core.projector``). The projector truncates each Gaussian where the ray's
  Mahalanobis distance exceeds ``extent`` (2-D), the medium where the point's does (3-D);
  both differ from the untruncated field by < rho exp(-extent^2/2) (4e-5 rho at 4.5),
  far below the Monte Carlo noise of any practical spp.
* ``grid``: the voxelised field (``mi_grg.core.voxelizer``) as a ``gridvolume`` in a
  ``heterogeneous`` medium. Its reference uses the SAME voxelised field: exp(-line
  integral of its trilinear interpolant), computed exactly by ``dr.dda.integrate`` on the
  edge-padded grid (``gridvolume`` clamps at the border) over the volume box. The
  difference to the closed form (the discretisation error) is reported separately as
  ``grid_vs_projector``.

Both media fill a ``cube`` with a ``null`` BSDF; the sensor is ``ct_scanner`` (one ray per
pixel centre, film [views * v, u]).
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

import mitsuba as mi

from mi_grg.core.gaussians import Gaussians
from mi_grg.core.geometry import Geometry

#: Largest number of (pixel, sample) lanes rendered in one ``mi.render`` pass.
MAX_LANES = 1 << 24


# ---------------------------------------------------------------- references
def _padded_volume(volume: np.ndarray, geometry: Geometry):
    """Edge-padded samples and the positions of the first/last ones ([x, y, z], length)."""
    vol = np.pad(np.asarray(volume, np.float32), 1, mode="edge")
    axes = geometry.voxel_axes()
    d = np.asarray(geometry.dVoxel)
    lo = np.array([a[0] for a in axes]) - d
    hi = np.array([a[-1] for a in axes]) + d
    return vol, lo, hi


def integrate_volume(volume, geometry: Geometry, angles=None) -> np.ndarray:
    """Line integrals [view, v, u] of a voxel volume [x, y, z] through every pixel centre.

    The field is the trilinear interpolant of the voxel-centre samples, constant beyond
    the outermost centres (what Mitsuba's ``gridvolume`` does with its default clamp),
    and zero outside the volume box. The integral over each ray's segment inside the box
    is exact for that interpolant (``dr.dda.integrate``, float32). Units: density x length.
    """
    import drjit.dda as dda
    vol = np.asarray(volume, np.float32)
    if vol.shape != tuple(geometry.nVoxel):
        raise ValueError(f"volume must have shape [x, y, z] = nVoxel = {geometry.nVoxel}, "
                         f"got {vol.shape}")
    if not np.all(np.isfinite(vol)):
        raise ValueError("volume contains NaN or Inf (expected finite densities)")
    padded, glo, ghi = _padded_volume(vol, geometry)
    o, d = geometry.pixel_rays_numpy(angles)
    shape = o.shape[:3]
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    # clip each ray to the volume box (slab method, float64)
    blo, bhi = geometry.bbox()
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0 = (blo - o) * inv
        t1 = (bhi - o) * inv
    t0 = np.where(np.isnan(t0), -np.inf, t0)
    t1 = np.where(np.isnan(t1), np.inf, t1)
    t_in = np.maximum(np.minimum(t0, t1).max(1), 0.0)
    t_out = np.maximum(t0, t1).min(1)
    length = np.maximum(t_out - t_in, 0.0)
    start = o + t_in[:, None] * d
    # drjit's dda indexes tensors in reversed (z, y, x) order: permute positions to match
    V = mi.Vector3f
    perm = [2, 1, 0]
    tensor = mi.TensorXf(np.ascontiguousarray(padded))
    ray_o = V(*[mi.Float(start[:, k]) for k in perm])
    ray_d = V(*[mi.Float(d[:, k]) for k in perm])
    res = dda.integrate(ray_o, ray_d, mi.Float(length), V(*[float(glo[k]) for k in perm]),
                        V(*[float(ghi[k]) for k in perm]), tensor)
    return np.asarray(res, np.float64).reshape(shape)


def closed_form_projection(gaussians: Gaussians, geometry: Geometry) -> np.ndarray:
    """Untruncated whole-line integrals [view, v, u] in float64 NumPy (fallback reference
    when ``mi_grg.core.projector`` is missing; O(N x pixels)):
    int rho exp(-(a t^2 + 2 b t + c)/2) dt = rho sqrt(2 pi / a) exp(-(c - b^2/a)/2)."""
    g = gaussians.numpy()
    pos, sc, q, rho = (g[k].astype(np.float64) for k in
                       ("positions", "scales", "rotations", "densities"))
    w, x, y, z = q.T
    R = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                  2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                  2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
                 -1).reshape(-1, 3, 3)
    A = np.einsum("nik,nk,njk->nij", R, 1.0 / sc ** 2, R)
    o, d = geometry.pixel_rays_numpy()
    out = np.zeros(o.shape[:3])
    for i in range(len(rho)):
        r = o - pos[i]
        a = np.einsum("...i,ij,...j->...", d, A[i], d)
        b = np.einsum("...i,ij,...j->...", d, A[i], r)
        c = np.einsum("...i,ij,...j->...", r, A[i], r)
        out += rho[i] * np.sqrt(2 * np.pi / a) * np.exp(-0.5 * np.maximum(c - b * b / a, 0.0))
    return out


def projection(gaussians: Gaussians, geometry: Geometry, extent=None) -> np.ndarray:
    """Line integrals [view, v, u] from the projector (closed form, float64 fallback)."""
    try:
        from mi_grg.core.projector import project, DEFAULT_EXTENT
    except ImportError:
        return closed_form_projection(gaussians, geometry)
    return np.asarray(project(gaussians, geometry, extent=DEFAULT_EXTENT if extent is None
                              else extent), np.float64)


# ---------------------------------------------------------------- Mitsuba scenes
def _box_transform(lo, hi):
    """to_world of Mitsuba's cube [-1, 1]^3 onto the box [lo, hi]."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return mi.ScalarTransform4f().translate((0.5 * (lo + hi)).tolist()).scale(
        (0.5 * (hi - lo)).tolist())


def _register_and_load(d: dict):
    from mi_grg.variant import set_variant
    set_variant(mi.variant())   # registers ct_scanner and gaussian_medium for this variant
    return mi.load_dict(d)


def _scene(geometry: Geometry, medium, lo, hi):
    """volpath scene: ct_scanner, constant emitter (I0 = 1), the medium in a null cube."""
    from mi_grg.data.scene import Scan, scanner_fields
    return _register_and_load({
        "type": "scene",
        # null scattering does not count as depth; albedo 0 ends a path at its first real
        # collision, so the depth limits never act (throughput stays 1 until then)
        "integrator": {"type": "volpath", "max_depth": -1, "rr_depth": 1 << 30},
        "sensor": {"type": "ct_scanner", **scanner_fields(Scan(geometry=geometry))},
        "emitter": {"type": "constant", "radiance": 1.0},
        "object": {"type": "cube", "to_world": _box_transform(lo, hi),
                   "bsdf": {"type": "null"}, "interior": medium},
    })


def grid_medium(volume: np.ndarray, geometry: Geometry) -> dict:
    """A purely absorbing ``heterogeneous`` medium whose sigma_t is ``volume`` [x, y, z]
    (1/length) on the geometry's volume box (``gridvolume``, trilinear, clamped)."""
    lo, hi = geometry.bbox()
    data = np.ascontiguousarray(np.transpose(np.asarray(volume, np.float32), (2, 1, 0))[..., None])
    return {"type": "heterogeneous", "albedo": 0.0, "scale": 1.0,
            "sigma_t": {"type": "gridvolume", "grid": mi.VolumeGrid(data),
                        "to_world": mi.ScalarTransform4f().translate(lo.tolist()).scale(
                            (hi - lo).tolist())}}


def render_transmittance(scene, spp: int, seed: int = 0) -> np.ndarray:
    """volpath estimate of T [view, v, u]: the mean of ``spp`` samples per pixel, rendered
    in passes of at most ``MAX_LANES`` lanes (each pass its own seed)."""
    sensor = scene.sensors()[0]
    pixels = int(np.prod(sensor.film().size()))
    per_pass = max(1, min(spp, MAX_LANES // max(pixels, 1)))
    acc, done, k = 0.0, 0, 0
    while done < spp:
        n = min(per_pass, spp - done)
        img = mi.render(scene, spp=n, seed=seed * 100003 + k)
        acc = acc + sensor.to_projections(np.asarray(img, np.float64)).astype(np.float64) * n
        done += n
        k += 1
    return acc / spp


def compare(mc: np.ndarray, ref_t: np.ndarray, spp: int) -> dict:
    """Error statistics of Monte Carlo transmittance ``mc`` against the exact ``ref_t``.

    Standard errors are the Bernoulli ones of the reference, sqrt(T (1 - T) / spp) per
    pixel; pixels with T = 1 (rays missing the object, error exactly 0) carry no
    information and are left out of the z statistics."""
    err = mc - ref_t
    se = np.sqrt(np.clip(ref_t * (1 - ref_t), 0, None) / spp)
    used = se > 0
    n = max(int(used.sum()), 1)
    se_mean = math.sqrt(float(np.sum(se[used] ** 2))) / n   # standard error of the mean error
    z = err[used] / se[used]
    return {"mean_error": float(err.mean()), "mean_abs_error": float(np.abs(err).mean()),
            "rms_error": float(np.sqrt(np.mean(err ** 2))),
            "mean_standard_error": float(se[used].mean()) if used.any() else 0.0,
            "standard_error_of_mean": se_mean,
            "z_mean": float(err[used].mean() / se_mean) if used.any() and se_mean > 0 else 0.0,
            "z_rms": float(np.sqrt(np.mean(z ** 2))) if used.any() else 0.0,
            "max_abs_z": float(np.abs(z).max()) if used.any() else 0.0,
            "pixels_used": int(used.sum())}


# ---------------------------------------------------------------- outputs
def _film(stack: np.ndarray) -> np.ndarray:
    """[view, v, u] -> the film layout [view * v, u] (views stacked vertically)."""
    s = np.asarray(stack, np.float32)
    return s.reshape(-1, s.shape[-1])


def _write(out_dir: Path, name: str, stack: np.ndarray, signed: bool) -> list:
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    img = _film(stack)
    exr = out_dir / f"{name}.exr"
    mi.Bitmap(np.ascontiguousarray(img)).write(str(exr))
    png = out_dir / f"{name}.png"
    if signed:
        m = float(np.abs(img).max()) or 1.0
        plt.imsave(png, img, cmap="RdBu_r", vmin=-m, vmax=m)
    else:
        plt.imsave(png, img, cmap="gray", vmin=0.0, vmax=1.0)
    return [str(exr), str(png)]


# ---------------------------------------------------------------- entry point
def _load(scene) -> tuple:
    """(gaussians, geometry) from a pair or from a scene XML whose ``id="object"`` is a
    ``gaussian_medium`` (its ``filename`` relative to the XML's folder)."""
    if isinstance(scene, (tuple, list)) and len(scene) == 2:
        gaussians, geometry = scene
        if not isinstance(gaussians, Gaussians) or not isinstance(geometry, Geometry):
            raise TypeError("render_crosscheck takes a scene path or (Gaussians, Geometry)")
        return gaussians, geometry
    from mi_grg.data.scene import load_scan
    path = Path(scene)
    scan = load_scan(path)  # resolves relative file names against the scene's folder
    obj = scan.object
    if obj.get("type") != "gaussian_medium" or "filename" not in obj:
        raise ValueError(f"{path}: the render cross-check needs the scanned object "
                         f"(id=\"object\") to be a <medium type=\"gaussian_medium\"> with a "
                         f"'filename' (Gaussians .npz); found {obj.get('type')!r}")
    npz = Path(obj["filename"])
    if not npz.is_absolute():
        npz = path.parent / npz
    return Gaussians.load_npz(npz), scan.geometry


def render_crosscheck(scene, spp: int, out_dir, seed: int = 0, extent=None,
                      routes=("gaussian", "grid")) -> dict:
    """Projector transmittance vs Mitsuba ``volpath`` Monte Carlo, per pixel.

    Args:
        scene: a scene XML path (``ct_scanner`` sensor + ``gaussian_medium`` object) or a
            ``(Gaussians, Geometry)`` pair.
        spp: samples per pixel of each Monte Carlo route.
        out_dir: folder for EXR and PNG images (film layout [view * v, u]):
            ``projector_T`` = exp(-projection), ``mc_<route>``, ``diff_<route>``
            (MC - reference), and for the grid route ``grid_T`` (its reference).
        seed: Monte Carlo seed.
        extent: truncation radius (Mahalanobis units; default: the projector's).
        routes: any of "gaussian" (direct Gaussian sum) and "grid" (voxelised field).
    Returns:
        A JSON-ready dict: per route the error statistics of ``compare`` (mean error,
        standard errors, z-scores) against its reference, the seconds taken, and
        ``grid_vs_projector`` (the voxelisation error of the grid route's reference).
    """
    from mi_grg.core.voxelizer import DEFAULT_EXTENT, voxelize
    spp = int(spp)
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    unknown = set(routes) - {"gaussian", "grid"}
    if unknown:
        raise ValueError(f"routes must be among ('gaussian', 'grid'), got {sorted(unknown)}")
    gaussians, geometry = _load(scene)
    extent = DEFAULT_EXTENT if extent is None else float(extent)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    t0 = time.perf_counter()
    proj = projection(gaussians, geometry, extent)
    t_proj = np.exp(-proj)
    files += _write(out, "projector_T", t_proj, signed=False)
    result = {"spp": spp, "seed": seed, "extent": extent, "n_gaussians": len(gaussians),
              "projection_shape": list(proj.shape),
              "projector_seconds": time.perf_counter() - t0, "routes": {}}
    if "gaussian" in routes:
        t0 = time.perf_counter()
        npz = out / "gaussians.npz"
        gaussians.save_npz(npz)
        medium = _register_and_load({"type": "gaussian_medium",
                                     "filename": str(npz.resolve()), "extent": extent})
        scn = _scene(geometry, medium, *_gaussian_box(medium, geometry))
        mc = render_transmittance(scn, spp, seed)
        stats = compare(mc, t_proj, spp)
        stats["seconds"] = time.perf_counter() - t0
        stats["majorant"] = float(medium.majorant)
        stats["reference"] = "exp(-projector)"
        files += _write(out, "mc_gaussian", mc, signed=False)
        files += _write(out, "diff_gaussian", mc - t_proj, signed=True)
        result["routes"]["gaussian"] = stats
    if "grid" in routes:
        t0 = time.perf_counter()
        vol = voxelize(gaussians, geometry, extent=extent)
        t_grid = np.exp(-integrate_volume(vol, geometry))
        lo, hi = geometry.bbox()
        mc = render_transmittance(_scene(geometry, grid_medium(vol, geometry), lo, hi),
                                  spp, seed + 1)
        stats = compare(mc, t_grid, spp)
        stats["seconds"] = time.perf_counter() - t0
        stats["reference"] = "exp(-dda integral of the same voxelised field)"
        stats["grid_vs_projector"] = {
            "max_abs_T_difference": float(np.abs(t_grid - t_proj).max()),
            "mean_abs_T_difference": float(np.abs(t_grid - t_proj).mean())}
        files += _write(out, "grid_T", t_grid, signed=False)
        files += _write(out, "mc_grid", mc, signed=False)
        files += _write(out, "diff_grid", mc - t_grid, signed=True)
        result["routes"]["grid"] = stats
    result["files"] = files
    (out / "crosscheck.json").write_text(json.dumps(result, indent=2))
    return result


def _gaussian_box(medium, geometry: Geometry):
    """Box for the gaussian_medium's cube: its Gaussians' box joined with the volume box."""
    lo, hi = geometry.bbox()
    return (np.minimum(lo, np.asarray(medium.bbox.min)),
            np.maximum(hi, np.asarray(medium.bbox.max)))
