"""Path-traced cross-check: Mitsuba's ``volpath`` vs the exact transmittance exp(-projection).

An X-ray projection is -log of the transmittance T = exp(-integral of sigma along the ray).
Mitsuba's ``volpath`` estimates T without any line integral: delta tracking through a
purely absorbing medium (albedo 0, spectrally flat extinction) lit by a ``constant``
emitter of radiance 1 (= I0), each sample is 1 (the path escaped) or 0 (absorbed), so the
per-pixel estimate is a binomial mean with standard error sqrt(T (1 - T) / spp).

Scene files (``render_scene``; ``mi-grg render SCENE``): the file is rendered as written
and its object (the ct_scanner's ``<medium>``) decides the reference (``REFERENCES``):
``ct_phantom`` -> the phantom's closed-form line integrals, ``gaussian_medium`` -> the
projector, ``heterogeneous`` with a ``gridvolume`` -> the exact line integral of the grid's
trilinear interpolant (``integrate_grid``). ``render_run`` (``mi-grg render --run``) writes
such a scene for a finished gr / r2 run. Per view: RMS / max difference, the expected
standard error, a z-score and pass/fail (``view_statistics``), crosscheck.json and
crosscheck.png.

``(Gaussians, Geometry)`` pairs (``render_crosscheck``, used by ``bench/speed_vs_error.py``)
take two routes through scenes built here:

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

Where it lives: ``crosscheck_stats`` (the per-view and per-pixel statistics),
``crosscheck_run`` (the scene of a finished gr / r2 run, ``mi-grg render --run``).
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

import mitsuba as mi

from mi_grg.core.gaussians import Gaussians
from mi_grg.core.geometry import Geometry

from mi_grg.evaluation.crosscheck_stats import (CONFIDENCE, binomial_z,  # noqa: F401
                                                compare, view_statistics)

#: Largest number of (pixel, sample) lanes rendered in one ``mi.render`` pass.
MAX_LANES = 1 << 24


# ---------------------------------------------------------------- references
def integrate_volume(volume, geometry: Geometry, angles=None) -> np.ndarray:
    """Line integrals [view, v, u] of a voxel volume [x, y, z] on ``geometry``'s voxel grid
    through every pixel centre (``integrate_grid`` over the volume box)."""
    shape = np.shape(volume)
    if tuple(shape) != tuple(geometry.nVoxel):
        raise ValueError(f"volume must have shape [x, y, z] = nVoxel = {geometry.nVoxel}, "
                         f"got {shape}")
    lo, hi = geometry.bbox()
    return integrate_grid(volume, lo, hi, geometry, angles)


def integrate_grid(volume, lo, hi, geometry: Geometry, angles=None) -> np.ndarray:
    """Line integrals [view, v, u] of a voxel grid [x, y, z] filling the box [lo, hi]
    (voxel centres at lo + (i + 1/2) (hi - lo) / n) through every pixel centre.

    The field is the trilinear interpolant of the voxel-centre samples, constant beyond
    the outermost centres (what Mitsuba's ``gridvolume`` does with its default clamp),
    and zero outside the box. The integral over each ray's segment inside the box is
    exact for that interpolant (``dr.dda.integrate``, float32). Units: density x length.
    """
    import drjit.dda as dda
    vol = np.asarray(volume, np.float32)
    if vol.ndim != 3:
        raise ValueError(f"volume must be 3-D [x, y, z], got shape {vol.shape}")
    if not np.all(np.isfinite(vol)):
        raise ValueError("volume contains NaN or Inf (expected finite densities)")
    blo, bhi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if not np.all(bhi > blo):
        raise ValueError(f"grid box must have hi > lo on every axis, got {blo} .. {bhi}")
    # edge padding: one more sample beyond each face, so the clamp needs no special case
    padded = np.pad(vol, 1, mode="edge")
    half = 0.5 * (bhi - blo) / np.asarray(vol.shape)
    glo, ghi = blo - half, bhi + half           # first/last padded sample positions
    o, d = geometry.pixel_rays_numpy(angles)
    shape = o.shape[:3]
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    # clip each ray to the box (slab method, float64)
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
def _pair(scene) -> tuple:
    """(gaussians, geometry) of a ``(Gaussians, Geometry)`` pair."""
    gaussians, geometry = scene
    if not isinstance(gaussians, Gaussians) or not isinstance(geometry, Geometry):
        raise TypeError("render_crosscheck takes a scene path or (Gaussians, Geometry)")
    return gaussians, geometry


def render_crosscheck(scene, spp: int, out_dir, seed: int = 0, extent=None,
                      routes=("gaussian", "grid")) -> dict:
    """Projector transmittance vs Mitsuba ``volpath`` Monte Carlo, per pixel.

    A scene XML path goes to ``render_scene`` (the file rendered as written, any object
    kind; ``extent`` and ``routes`` do not apply). For a ``(Gaussians, Geometry)`` pair:

    Args:
        scene: a ``(Gaussians, Geometry)`` pair (or a scene path, see above).
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
    if not (isinstance(scene, (tuple, list)) and len(scene) == 2):
        return render_scene(scene, spp, out_dir, seed=seed)
    spp = int(spp)
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    unknown = set(routes) - {"gaussian", "grid"}
    if unknown:
        raise ValueError(f"routes must be among ('gaussian', 'grid'), got {sorted(unknown)}")
    gaussians, geometry = _pair(scene)
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


# ---------------------------------------------------------------- a scene file, as written
#: The scanned objects (the ``<medium>`` of the ct_scanner) the scene route can check, and
#: what each is compared against.
REFERENCES = {
    "ct_phantom": "exp(-exact line integral of the phantom) (mi_grg.data.phantoms)",
    "gaussian_medium": "exp(-projector) (mi_grg.core.projector, closed form)",
    "heterogeneous": "exp(-exact line integral of the gridvolume's trilinear interpolant)",
}
#: How to make a scene this route accepts.
SCENE_HINT = ("a render scene is a <sensor type=\"ct_scanner\"> with the scanned <medium> "
              "inside it, <integrator type=\"volpath\"/> and <emitter type=\"constant\">; "
              "copy scenes/shepp_cone_volpath.xml")
#: Confidence of each view's pass/fail (two-sided; see ``view_statistics``).
ESTIMATOR = ("volpath on a pure absorber (albedo 0, spectrally flat extinction) does delta "
             "tracking: every sample is 1 (escaped to the emitter) or 0 (absorbed), so a "
             "pixel is a binomial count: SE = sqrt(T (1 - T) / spp) with T the reference; "
             "checked: every sample of a 1-spp pass is 0 or 1")


def _bad(path, message):
    from mi_grg.data.scene import ScanError
    return ScanError(f"{path}: {message}")


def load_render_scene(path):
    """(scan, Mitsuba scene) of a cross-check scene file, checked.

    Raises ``ScanError`` (a ValueError; one line naming what is missing and how to add it)
    for a scene without a ct_scanner sensor, without a scanned object, with an integrator
    other than ``volpath``, without a ``constant`` emitter (or with other objects), or with
    an object that is not a pure absorber of a supported kind (``REFERENCES``)."""
    from mi_grg.data.scene import ScanError, load_scan_and_scene
    path = Path(path)
    try:
        scan, scene = load_scan_and_scene(path)
    except ScanError as e:
        raise ScanError(f"{e}; {SCENE_HINT}") from None
    kinds = " | ".join(f'<medium type="{k}">' for k in REFERENCES) + " (with a gridvolume)"
    if not scan.object:
        raise _bad(path, f"the ct_scanner sensor holds no scanned object: put {kinds} "
                         "inside <sensor type=\"ct_scanner\"> (see scenes/*_volpath.xml)")
    kind = scan.object["type"]
    if kind not in REFERENCES:
        raise _bad(path, f"cannot cross-check a <medium type=\"{kind}\">: the object must be "
                         f"one of {kinds} (see scenes/*_volpath.xml)")
    integrator = scan.integrator.get("type")
    if integrator != "volpath":
        raise _bad(path, f"{'no integrator' if integrator is None else f'integrator {integrator!r}'}"
                         ": the cross-check needs Mitsuba's volumetric path tracer; put "
                         "<integrator type=\"volpath\"/> at the top level of the scene")
    emitters = [o for o in scan.other if o.get("type") == "constant"]
    extra = [o["type"] for o in scan.other if o.get("type") != "constant"]
    if len(emitters) != 1 or extra:
        raise _bad(path, "the cross-check needs exactly one <emitter type=\"constant\"> (the "
                         "unattenuated beam) and nothing else at the top level; found "
                         f"{[o['type'] for o in scan.other] or 'none'}. Add <emitter type="
                         "\"constant\"><float name=\"radiance\" value=\"1\"/></emitter>")
    radiance = emitters[0].get("radiance", 1.0)
    if isinstance(radiance, bool) or not isinstance(radiance, (int, float)) or not radiance > 0:
        raise _bad(path, f"the constant emitter's radiance must be one number > 0 (the "
                         f"beam intensity I0), got {radiance!r}")
    if kind == "heterogeneous":
        _check_grid_object(path, scan.object)
    if kind == "gaussian_medium" and "filename" not in scan.object:
        raise _bad(path, "<medium type=\"gaussian_medium\"> needs <string name=\"filename\"> "
                         "(a Gaussians .npz, e.g. a run's gaussians.npz)")
    medium = scene.sensors()[0].get_medium()
    if medium.has_spectral_extinction():
        # volpath then weights each sample by transmittance / free-flight pdf, which is 0
        # for a ray leaving the medium into a scene without shapes: every pixel renders 0
        raise _bad(path, f"the <medium type=\"{kind}\"> has spectral extinction; add "
                         "<boolean name=\"has_spectral_extinction\" value=\"false\"/> to it")
    return scan, scene


def _check_grid_object(path, obj) -> None:
    """A ``heterogeneous`` medium that the grid reference describes exactly."""
    albedo = obj.get("albedo", None)
    if isinstance(albedo, dict) or albedo is None or float(albedo) != 0.0:
        raise _bad(path, "the heterogeneous medium must be a pure absorber: add <float "
                         f"name=\"albedo\" value=\"0\"/> (found {albedo!r}; Mitsuba's "
                         "default is 0.75)")
    sigma = obj.get("sigma_t")
    if not isinstance(sigma, dict) or sigma.get("type") != "gridvolume":
        raise _bad(path, "the heterogeneous medium's sigma_t must be a <volume "
                         "type=\"gridvolume\" name=\"sigma_t\"> (a .vol file)")
    allowed = {"type": None, "filename": None, "to_world": None, "raw": None,
               "filter_type": "trilinear", "wrap_mode": "clamp", "use_grid_bbox": False}
    for key, value in sigma.items():
        if key not in allowed or (allowed[key] is not None and value != allowed[key]):
            raise _bad(path, f"gridvolume {key}={value!r} is not supported by the exact "
                             f"reference (trilinear, clamped, placed by to_world)")


def _grid_box(to_world) -> tuple:
    """(lo, hi) of the unit cube under ``to_world``, which must be a scale + translation."""
    m = np.asarray(to_world.matrix, np.float64) if to_world is not None else np.eye(4)
    lin = m[:3, :3]
    if np.any(np.abs(lin - np.diag(np.diag(lin))) > 1e-6 * np.abs(lin).max()) or \
            np.any(np.diag(lin) <= 0):
        raise ValueError("gridvolume to_world must be a positive scale and a translation "
                         f"(axis-aligned box), got matrix {m[:3].tolist()}")
    lo = m[:3, 3]
    return lo, lo + np.diag(lin)


def scene_reference(scan, scene) -> tuple:
    """(exact transmittance [view, v, u] float64, description) of a checked scene."""
    import drjit as dr
    obj, geo = scan.object, scan.geometry
    kind = obj["type"]
    medium = scene.sensors()[0].get_medium()
    info = {"object": kind, "reference": REFERENCES[kind]}
    if kind == "ct_phantom":
        from mi_grg.data.phantoms import make_phantom
        proj = make_phantom(obj["phantom"], seed=int(obj.get("seed", 0))).line_integrals(geo)
        info["phantom"] = obj["phantom"]
    elif kind == "gaussian_medium":
        from mi_grg.core.voxelizer import DEFAULT_EXTENT
        g = Gaussians.load_npz(medium.filename)     # as resolved by the plugin
        extent = float(obj.get("extent", DEFAULT_EXTENT))
        proj = float(obj.get("scale", 1.0)) * projection(g, geo, extent)
        info.update(gaussians=os.path.normpath(medium.filename), n_gaussians=len(g),
                    extent=extent)
    else:
        params = mi.traverse(medium)
        data = np.asarray(params["sigma_t.data"], np.float32)   # [z, y, x, channels]
        if data.ndim != 4 or data.shape[-1] != 1:
            raise ValueError(f"gridvolume must hold one channel, got data shape {data.shape}")
        vol = np.transpose(data[..., 0], (2, 1, 0))
        if vol.min() < 0:
            raise ValueError(f"gridvolume sigma_t must be >= 0, has minimum {vol.min()}")
        lo, hi = _grid_box(obj["sigma_t"].get("to_world"))
        proj = float(params["scale"]) * integrate_grid(vol, lo, hi, geo)
        info.update(grid_shape=list(vol.shape), box=[lo.tolist(), hi.tolist()])
    dr.eval()
    return np.exp(-np.asarray(proj, np.float64)), info


def _render_checked(scene, spp: int, seed: int, radiance: float) -> np.ndarray:
    """volpath transmittance [view, v, u] (mean of ``spp`` samples, divided by the beam's
    radiance). The first sample of every pixel is rendered alone and must be 0 or 1: the
    binomial standard errors of ``view_statistics`` rest on it."""
    sensor = scene.sensors()[0]
    first = sensor.to_projections(mi.render(scene, spp=1, seed=seed * 100003 + 100002))
    first = first.astype(np.float64) / radiance
    if not np.all((first == 0) | (np.abs(first - 1) < 1e-6)):
        bad = first[(first != 0) & (np.abs(first - 1) >= 1e-6)]
        raise ValueError(f"volpath's samples are not 0 or 1 (e.g. {bad[:3].tolist()}): the "
                         "object is not a pure absorber under delta tracking, so the binomial "
                         "standard error does not apply")
    if spp == 1:
        return first
    rest = render_transmittance(scene, spp - 1, seed) / radiance
    return (first + rest * (spp - 1)) / spp


def render_scene(path, spp: int, out_dir, seed: int = 0, confidence: float = CONFIDENCE,
                 extra: dict | None = None, shown=None) -> dict:
    """Render a scene file as written with Mitsuba's ``volpath`` and compare each view's
    transmittance with the exact one of its object (``REFERENCES``).

    Writes ``crosscheck.json`` (the returned dict: per view RMS / max difference, the
    expected Monte Carlo standard error, z, pass) and ``crosscheck.png`` (per view:
    volpath, reference, difference in standard errors as ``binomial_z``) into ``out_dir``, plus both
    transmittance stacks as EXR (film layout [view * v, u]). ``extra`` is merged into the
    JSON (e.g. the run a scene was built from); ``shown``: the folder that ``out_dir`` (a
    temporary) becomes, named in the JSON instead."""
    from mi_grg.evaluation.plotting import crosscheck_figure
    spp = int(spp)
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    if not 0.5 < float(confidence) < 1.0:
        raise ValueError(f"confidence must lie in (0.5, 1), got {confidence}")
    out, shown = Path(out_dir), Path(out_dir if shown is None else shown)
    named = shown / Path(path).name if Path(path).parent == out else path
    t0 = time.perf_counter()
    scan, scene = load_render_scene(path)
    _check_memory(scan.geometry, spp, named)
    ref, info = scene_reference(scan, scene)
    t_ref = time.perf_counter() - t0
    radiance = float(next(o for o in scan.other if o["type"] == "constant").get("radiance", 1.0))
    t0 = time.perf_counter()
    mc = _render_checked(scene, spp, seed, radiance)
    t_mc = time.perf_counter() - t0
    views = view_statistics(mc, ref, spp, confidence)
    angles = np.asarray(scan.geometry.angles, np.float64)
    for v, a in zip(views, angles):
        v["angle_deg"] = float(np.degrees(a))
    from scipy.stats import norm
    result = {"scene": str(named), **info, "spp": spp, "seed": seed,
              "projection_shape": list(ref.shape), "estimator": ESTIMATOR,
              "confidence": float(confidence),
              "z_critical": float(norm.ppf(1 - (1 - confidence) / 2)),
              "pass": all(v["pass"] for v in views), "views": views,
              "reference_seconds": t_ref, "volpath_seconds": t_mc, **(extra or {})}
    out.mkdir(parents=True, exist_ok=True)
    for name, stack in (("volpath_T", mc), ("reference_T", ref)):
        mi.Bitmap(np.ascontiguousarray(_film(stack))).write(str(out / f"{name}.exr"))
    crosscheck_figure(out / "crosscheck.png", mc, ref, binomial_z(mc, ref, spp), result)
    result["files"] = [str(shown / f) for f in ("volpath_T.exr", "reference_T.exr",
                                                  "crosscheck.png", "crosscheck.json")]
    (out / "crosscheck.json").write_text(json.dumps(result, indent=2))
    return result


def _check_memory(geometry: Geometry, spp: int, path) -> None:
    """Refuse a render whose film and images would not fit (``mi_grg.core.memory``)."""
    from mi_grg.core import memory
    memory.check([memory.film(geometry.n_views, geometry.nDetector, spp, MAX_LANES),
                  memory.projections(geometry.n_views, geometry.nDetector, copies=12,
                                     what="transmittance images")],
                 str(path), lower="lower the detector size (--det), the views or --spp")
