"""Simulated CT cases from voxel volumes (the real 3-D data in ``shared/data``).

The object. A source volume ``src`` [X, Y, Z] (e.g. 128^3) spans the geometry's volume box
(``sVoxel`` centred at ``offOrigin``), whatever the reconstruction grid ``nVoxel`` is. The
continuous object is its **trilinear interpolant** between source voxel centres, clamped to
the edge values inside the box (continuous index q in [-1/2, n - 1/2], values beyond the
outer centres held constant) and **zero outside the box**. Trilinear interpolation with
clamping is separable: f(x, y, z) = sum_ijk src[i, j, k] phi_i(x) phi_j(y) phi_k(z).

Projections (``volume_line_integrals``). Each detector pixel's ray (``Geometry.rays``, the
one ray formula) is clipped exactly to the box (slab method); the chord [t0, t1] is cut
into N = ceil((t1 - t0) / h) equal segments and integrated with the midpoint rule, i.e. N
trilinear samples (8 gathers each) times the segment length (<= h). The step is
``h = min(source voxel size) / oversample``; the default ``oversample = 4`` gives a step of
1/4 of a 128^3 voxel (2 / 512 = 0.0039 in normalised units). This is *not* the Joseph
projector that SART / ASD-POCS / FDK initialisation use (one bilinear sample per voxel
plane on the reconstruction grid), so no method is scored with its own forward model.
Accuracy (tests/test_volume_phantom.py): exact for a constant volume (float32 round-off),
and halving the step from 1/4 to 1/8 voxel changes projections by < 2e-3 of their maximum.

Ground truth on the reconstruction grid (``ground_truth``):
  * ``"average"`` (default): the exact average of the continuous object over each
    reconstruction voxel (separable 1-D weights integrated in closed form). For 128^3 -> 64^3
    this is the 2x block average of the source volume smoothed by the 1-D kernel
    [1, 7, 7, 1] / 16 per axis, i.e. exactly what the projections were taken of.
  * ``"block"``: the plain block average of the source voxels (needs nVoxel dividing the
    source shape); the piecewise-constant reading of the source, slightly sharper than the
    projected object.

Noise: ``NoiseModel`` (TIGRE CTnoise) on the training views only, drawn from
``np.random.default_rng([seed, 1])`` as in ``mi_grg.data.simulate``; test views are exact.
"""
from __future__ import annotations

import hashlib
import math
import os
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_grg.data.case import Case
from mi_grg.core.geometry import Geometry
from mi_grg.data.noise import NoiseModel

DATA_ENV = "MI_GRG_DATA"
DEFAULT_OVERSAMPLE = 4          # samples per source voxel length (step = voxel / 4)
MAX_RAYS = 1 << 20              # rays per kernel launch (bounds temporary memory)
GT_MODES = ("average", "block")


# ---------------------------------------------------------------- data files
def data_dir() -> Path:
    """The directory holding the shared voxel volumes.

    ``$MI_GRG_DATA`` if set, else ``<repo root>/../shared/data``; raises FileNotFoundError
    naming both when neither exists."""
    env = os.environ.get(DATA_ENV)
    default = (Path(__file__).resolve().parents[2] / ".." / "shared" / "data").resolve()
    if env:
        p = Path(env).expanduser()
        if p.is_dir():
            return p
        raise FileNotFoundError(f"${DATA_ENV} = {env!r} is not a directory (unset it to use "
                                f"the default {default})")
    if default.is_dir():
        return default
    raise FileNotFoundError(f"no data directory: set ${DATA_ENV} or create {default} "
                            f"(the repository's ../shared/data)")


def resolve_volume_path(name) -> Path:
    """A path as given if it exists, else ``data_dir() / name``."""
    p = Path(name).expanduser()
    if p.is_file():
        return p.resolve()
    q = data_dir() / str(name)
    if q.is_file():
        return q
    raise FileNotFoundError(f"voxel volume {name!r} not found (looked at {p} and {q})")


def provenance(path: Path) -> dict:
    """What / source / licence of a data file, from the README table in its directory."""
    path = Path(path)
    out = {"file": path.name, "provenance": str(path.parent / "README.md")}
    readme = path.parent / "README.md"
    if readme.is_file():
        for line in readme.read_text(encoding="utf-8", errors="replace").splitlines():
            cols = [c.strip() for c in line.strip().strip("|").split("|")]
            if len(cols) >= 4 and cols[0] == path.name:
                out.update({"what": cols[1], "origin": cols[2].replace("`", ""),
                            "licence": cols[3]})
                break
    if "licence" not in out:
        out["licence"] = f"unknown: not listed in {readme}"
    return out


def load_volume(source) -> tuple[np.ndarray, dict]:
    """(float32 C-contiguous [x, y, z], info) from an array or a ``.npy`` path / data name."""
    if isinstance(source, (str, os.PathLike)):
        path = resolve_volume_path(source)
        vol = np.load(path, allow_pickle=False)
        with open(path, "rb") as f:
            digest = hashlib.sha256(f.read()).hexdigest()
        info = {**provenance(path), "sha256": digest}
    else:
        vol, info = np.asarray(source), {"file": None, "provenance": "array passed in",
                                          "licence": "n/a"}
    vol = np.ascontiguousarray(vol, dtype=np.float32)
    if vol.ndim != 3 or min(vol.shape) < 2:
        raise ValueError(f"volume must be 3-D [x, y, z] with >= 2 voxels per axis, got "
                         f"shape {vol.shape}")
    if not np.all(np.isfinite(vol)):
        raise ValueError("volume contains NaN or Inf (expected finite densities, 1/length)")
    info["shape"] = list(vol.shape)
    return vol, info


# ---------------------------------------------------------------- projector
def _step(geometry: Geometry, src_shape, oversample: float) -> float:
    if not (isinstance(oversample, (int, float)) and math.isfinite(oversample)
            and oversample > 0):
        raise ValueError(f"oversample (samples per source voxel) must be > 0, got "
                         f"{oversample!r}")
    d = np.asarray(geometry.sVoxel, np.float64) / np.asarray(src_shape)
    return float(d.min() / oversample)


def volume_line_integrals(volume, geometry: Geometry, angles=None,
                          oversample: float = DEFAULT_OVERSAMPLE) -> np.ndarray:
    """Line integrals [view, v, u] (float32, density x length) of the trilinear object of
    ``volume`` [X, Y, Z] spanning ``geometry``'s box; see the module docstring.

    Args:
        volume: source densities [X, Y, Z] (any shape >= 2 per axis, independent of
            ``geometry.nVoxel``), 1/length.
        geometry: the scan; ``angles`` (radians) overrides ``geometry.angles``.
        oversample: samples per source voxel length; step = min(sVoxel / shape) / oversample.
    """
    vol, _ = load_volume(volume)
    a = np.asarray(geometry.angles if angles is None else angles, np.float64).reshape(-1)
    if a.size == 0 or not np.all(np.isfinite(a)):
        raise ValueError("angles must be a non-empty array of finite radians")
    h = _step(geometry, vol.shape, oversample)
    nv, nu = geometry.nDetector
    n_pix = nv * nu
    tex = mi.Float(vol.reshape(-1))
    per = max(1, MAX_RAYS // n_pix)
    out = np.empty((a.size, nv, nu), np.float32)
    for v0 in range(0, a.size, per):
        v1 = min(a.size, v0 + per)
        res = _march_kernel(tex, vol.shape, geometry, a[v0:v1], h)
        out[v0:v1] = np.array(res.numpy(), copy=True).reshape(v1 - v0, nv, nu)
    return out


def _box_clip(o, d, lo, hi, parallel):
    """Slab clipping of rays o + t d against [lo, hi]; returns (t0, t1) (t1 <= t0: miss)."""
    Float = mi.Float
    t0 = Float(-dr.inf) if parallel else Float(0.0)
    t1 = Float(dr.inf)
    for k in range(3):
        flat = dr.abs(d[k]) < 1e-12
        inside = (o[k] >= lo[k]) & (o[k] <= hi[k])
        inv = 1.0 / dr.select(flat, 1.0, d[k])
        ta = (lo[k] - o[k]) * inv
        tb = (hi[k] - o[k]) * inv
        near = dr.select(flat, dr.select(inside, -dr.inf, dr.inf), dr.minimum(ta, tb))
        far = dr.select(flat, dr.select(inside, dr.inf, -dr.inf), dr.maximum(ta, tb))
        t0 = dr.maximum(t0, near)
        t1 = dr.minimum(t1, far)
    return t0, t1


def _march_kernel(tex, shape, geo: Geometry, angles, h):
    """One kernel: midpoint-rule trilinear ray marching for every pixel of ``angles``."""
    Float, UInt = mi.Float, mi.UInt32
    nv, nu = geo.nDetector
    n_pix = nv * nu
    n_rays = len(angles) * n_pix
    box = geo.bbox()
    # python floats: numpy scalars on the left of Dr.Jit arrays would broadcast to ndarrays
    lo, hi = [float(x) for x in box[0]], [float(x) for x in box[1]]
    dsrc = [(hi[k] - lo[k]) / shape[k] for k in range(3)]
    r = dr.arange(UInt, n_rays)
    view, pix = r // n_pix, r % n_pix
    o, d, _ = geo.rays_of_views(geo.view_tables(angles), view, Float(pix // nu) + 0.5,
                                Float(pix % nu) + 0.5)
    t0, t1 = _box_clip(o, d, lo, hi, geo.mode == "parallel")
    length = dr.maximum(t1 - t0, 0.0)
    n_seg = UInt(dr.ceil(length / h))
    dt = length / dr.maximum(Float(n_seg), 1.0)
    # start in continuous source-index space (centres at integers), per unit t
    q0 = [(o[k] + t0 * d[k] - lo[k]) / dsrc[k] - 0.5 for k in range(3)]
    e = [d[k] / dsrc[k] for k in range(3)]
    acc = _accumulate(tex, shape, q0, e, dt, n_seg)
    return acc * dt


def _trilinear(tex, shape, q):
    """Clamped trilinear sample of ``tex`` (flat [x, y, z]) at continuous indices ``q``."""
    Float, UInt, Int = mi.Float, mi.UInt32, mi.Int32
    idx, frac = [], []
    for k in range(3):
        qk = dr.clip(q[k], 0.0, shape[k] - 1.0)
        ik = dr.minimum(Int(dr.floor(qk)), shape[k] - 2)   # so that ik + 1 <= n - 1
        idx.append(UInt(ik))
        frac.append(qk - Float(ik))
    sx, sy = shape[1] * shape[2], shape[2]
    base = idx[0] * sx + idx[1] * sy + idx[2]
    fx, fy, fz = frac
    gx, gy, gz = 1.0 - fx, 1.0 - fy, 1.0 - fz

    def g(off):
        return dr.gather(Float, tex, base + off)
    c00 = dr.fma(fz, g(1), gz * g(0))
    c01 = dr.fma(fz, g(sy + 1), gz * g(sy))
    c10 = dr.fma(fz, g(sx + 1), gz * g(sx))
    c11 = dr.fma(fz, g(sx + sy + 1), gz * g(sx + sy))
    return gx * (gy * c00 + fy * c01) + fx * (gy * c10 + fy * c11)


@dr.syntax
def _accumulate(tex, shape, q0, e, dt, n_seg):
    """Sum of trilinear samples at segment midpoints t = (i + 1/2) dt, i < n_seg (per ray)."""
    Float, UInt = mi.Float, mi.UInt32
    i = UInt(0)
    acc = dr.zeros(Float, dr.width(dt))
    # Kahan compensation: chords hold up to ~1000 samples; keeps the float32 sums exact
    # enough that step-halving differences measure discretisation, not round-off.
    comp = dr.zeros(Float, dr.width(dt))
    while i < n_seg:
        t = (Float(i) + 0.5) * dt
        val = _trilinear(tex, shape, [dr.fma(t, e[k], q0[k]) for k in range(3)])
        y = val - comp
        s = acc + y
        comp = (s - acc) - y
        acc = s
        i += 1
    return acc


# ---------------------------------------------------------------- ground truth
def _interval_weights(n_src: int, n_out: int) -> np.ndarray:
    """[n_out, n_src] float64: W[j, i] = mean over output cell j of phi_i, the clamped
    linear-interpolation basis of source sample i (both grids span the same interval)."""
    r = n_src / n_out
    W = np.zeros((n_out, n_src))
    for j in range(n_out):
        # output cell j in source continuous-index space (centres at integers)
        a, b = j * r - 0.5, (j + 1) * r - 0.5
        cuts = np.concatenate([[a], np.arange(math.floor(a) + 1, math.ceil(b)), [b]])
        cuts = np.unique(np.clip(cuts, a, b))
        for lo_, hi_ in zip(cuts[:-1], cuts[1:]):
            m = 0.5 * (lo_ + hi_)   # the basis is linear on [lo_, hi_]: midpoint is exact
            q = min(max(m, 0.0), n_src - 1.0)
            i0 = min(int(math.floor(q)), n_src - 2)
            f = q - i0
            W[j, i0] += (hi_ - lo_) * (1.0 - f)
            W[j, i0 + 1] += (hi_ - lo_) * f
        W[j] /= (b - a)
    return W


def average_to_grid(volume, n_out) -> np.ndarray:
    """Exact mean of the clamped trilinear object of ``volume`` [X, Y, Z] over each voxel
    of an ``n_out`` = (nx, ny, nz) grid spanning the same box; float32 [nx, ny, nz]."""
    vol, _ = load_volume(volume)
    n_out = tuple(int(n) for n in n_out)
    out = vol.astype(np.float64)
    for axis in range(3):
        W = _interval_weights(vol.shape[axis], n_out[axis])
        out = np.moveaxis(np.tensordot(W, out, axes=([1], [axis])), 0, axis)
    return out.astype(np.float32)


def block_average(volume, n_out) -> np.ndarray:
    """Plain block mean of ``volume`` [X, Y, Z] down to ``n_out`` (must divide the shape)."""
    vol, _ = load_volume(volume)
    n_out = tuple(int(n) for n in n_out)
    if any(s % n for s, n in zip(vol.shape, n_out)):
        raise ValueError(f"block averaging needs nVoxel {n_out} to divide the source shape "
                         f"{vol.shape}; use ground_truth='average'")
    f = [s // n for s, n in zip(vol.shape, n_out)]
    return vol.reshape(n_out[0], f[0], n_out[1], f[1], n_out[2], f[2]).mean(
        axis=(1, 3, 5), dtype=np.float64).astype(np.float32)


# ---------------------------------------------------------------- cases
def simulate_volume_case(source, geometry: Geometry, test_angles=None,
                         noise: NoiseModel | None = None, seed: int = 0,
                         oversample: float = DEFAULT_OVERSAMPLE,
                         ground_truth: str = "average") -> Case:
    """A simulated case (file units, ``scene_scale = 1``) from a voxel volume.

    Args:
        source: a ``.npy`` path, a file name in ``data_dir()`` (e.g. "bone_128.npy") or an
            array [X, Y, Z]; it spans the geometry's volume box.
        geometry: scan geometry (training angles); ``nVoxel`` is the reconstruction grid.
            Its detector should cover the box's whole shadow (``default_geometry`` does).
        test_angles: radians; None -> ``mi_grg.data.simulate.default_test_angles(n_train)``;
            empty -> no test views.
        noise: ``NoiseModel`` on the training views only (None: exact).
        seed: noise seed (``np.random.default_rng([seed, 1])``).
        oversample: samples per source voxel length (step = voxel / oversample).
        ground_truth: "average" or "block" (module docstring).
    Returns:
        Case with float32 train/test [view, v, u], vol_gt [x, y, z] = nVoxel and ``info``
        recording the source file, its provenance and licence, and the sampling.
    """
    from mi_grg.data.simulate import scan_fields, simulated_views
    if not isinstance(geometry, Geometry):
        raise TypeError(f"geometry must be a mi_grg.Geometry, got {type(geometry).__name__}")
    if noise is not None and not isinstance(noise, NoiseModel):
        raise TypeError(f"noise must be a NoiseModel or None, got {type(noise).__name__}")
    if ground_truth not in GT_MODES:
        raise ValueError(f"ground_truth must be one of {GT_MODES}, got {ground_truth!r}")
    vol, src_info = load_volume(source)
    seed = int(seed)
    h = _step(geometry, vol.shape, oversample)
    train, test, test_angles = simulated_views(
        lambda g, a=None: volume_line_integrals(vol, g, a, oversample=oversample), geometry,
        test_angles, noise, seed)
    gt = (average_to_grid(vol, geometry.nVoxel) if ground_truth == "average"
          else block_average(vol, geometry.nVoxel))
    info = {
        "source": "mi_grg.data.volume_phantom",
        "volume": src_info,
        "sampling": {
            "object": "trilinear interpolant of the source voxels, clamped to the edge "
                      "values inside the volume box, zero outside",
            "projector": "ray-driven, exact box clipping, midpoint rule with equal segments "
                         "<= step, trilinear samples (not the Joseph projector)",
            "oversample": float(oversample), "step": h,
            "step_in_source_voxels": 1.0 / float(oversample),
            "ground_truth": ("exact voxel average of the trilinear object"
                             if ground_truth == "average" else
                             "block average of the source voxels"),
        },
        "noise": None if noise is None else noise.to_dict(),
        "seed": seed,
        **scan_fields(geometry, test_angles),
    }
    return Case(geometry=geometry, train=train, test_angles=test_angles, test=test, vol_gt=gt,
                scene_scale=1.0, info=info)
