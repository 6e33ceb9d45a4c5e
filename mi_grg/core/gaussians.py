"""Radiative Gaussians: the one type that holds them, their activations and covariance.

sigma(x) = sum_i rho_i exp(-1/2 (x - p_i)^T Sigma_i^-1 (x - p_i)),
Sigma_i = R_i S_i S_i^T R_i^T, S_i = diag(scales_i), R_i from the unit quaternion q_i.

Physical parameters are stored as Dr.Jit arrays of the active variant:
    positions [N, 3] (mi.Point3f), scales [N, 3] (mi.Vector3f, > 0),
    rotations [N, 4] (mi.Vector4f, unit quaternion ordered w, x, y, z),
    densities [N] (mi.Float, >= 0).
Training optimises unconstrained *raw* parameters; the activations between the two live
here only (``to_raw`` / ``from_raw``):
    density = softplus(raw_density), scale = exp(raw_scale), rotation = raw / |raw|.
The validity checks that the projector and the voxelizer run on every call
(``gaussian_checks``, ``first_failure``) live here too.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

QUATERNION_TOL = 1e-3  # accepted | |q| - 1 | for user-given rotations


class GaussiansError(ValueError):
    """Invalid Gaussian parameters; the message names the field."""


def _as_numpy(name, value, shape_tail):
    kind = np.asarray(value).dtype.kind
    if kind not in "fiu":
        raise GaussiansError(f"{name} must hold real numbers, got dtype "
                             f"{np.asarray(value).dtype}")
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 1 and shape_tail == ():
        pass
    elif arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        want = "[N" + "".join(f", {s}" for s in shape_tail) + "]"
        raise GaussiansError(f"{name} must have shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise GaussiansError(f"{name} contains NaN or Inf")
    return arr


@dataclass
class Gaussians:
    """A set of N radiative Gaussians (Dr.Jit arrays; see the module docstring)."""

    positions: object   # mi.Point3f  [N, 3]
    scales: object      # mi.Vector3f [N, 3]
    rotations: object   # mi.Vector4f [N, 4] (w, x, y, z)
    densities: object   # mi.Float    [N]

    def __len__(self) -> int:
        return dr.width(self.densities) if dr.width(self.densities) else 0

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_numpy(cls, positions, scales, rotations=None, densities=None) -> "Gaussians":
        """Validated construction from arrays: positions [N, 3], scales [N, 3] (> 0),
        rotations [N, 4] unit quaternions (w, x, y, z; default identity), densities [N]
        (>= 0; default 1)."""
        p = _as_numpy("positions", positions, (3,))
        n = p.shape[0]
        s = _as_numpy("scales", scales, (3,))
        if s.shape[0] != n:
            raise GaussiansError(f"scales has {s.shape[0]} rows, positions has {n}")
        if np.any(s <= 0):
            raise GaussiansError("scales must be > 0 (they are standard deviations)")
        if rotations is None:
            q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        else:
            q = _as_numpy("rotations", rotations, (4,))
            if q.shape[0] != n:
                raise GaussiansError(f"rotations has {q.shape[0]} rows, positions has {n}")
            norm = np.linalg.norm(q, axis=1)
            if np.any(norm == 0):
                raise GaussiansError("rotations contains a zero quaternion")
            if np.any(np.abs(norm - 1) > QUATERNION_TOL):
                raise GaussiansError(
                    "rotations must be unit quaternions (w, x, y, z); "
                    f"max | |q| - 1 | = {np.abs(norm - 1).max():.3g}. Normalise them first.")
            q = q / norm[:, None]
        if densities is None:
            d = np.ones(n)
        else:
            d = _as_numpy("densities", densities, ())
            if d.shape != (n,):
                raise GaussiansError(f"densities must have shape [{n}], got {d.shape}")
            if np.any(d < 0):
                raise GaussiansError("densities must be >= 0")
        return cls(positions=mi.Point3f(*[mi.Float(p[:, k]) for k in range(3)]),
                   scales=mi.Vector3f(*[mi.Float(s[:, k]) for k in range(3)]),
                   rotations=mi.Vector4f(*[mi.Float(q[:, k]) for k in range(4)]),
                   densities=mi.Float(d))

    def numpy(self) -> dict:
        """Float32 NumPy copies: positions [N,3], scales [N,3], rotations [N,4], densities [N]."""
        def stack(v):
            return np.stack([np.asarray(c, np.float32) for c in v], axis=-1) if len(self) \
                else np.zeros((0, len(v)), np.float32)
        return {"positions": stack(self.positions), "scales": stack(self.scales),
                "rotations": stack(self.rotations),
                "densities": np.asarray(self.densities, np.float32).reshape(-1)}

    def replace(self, **changes) -> "Gaussians":
        return dataclasses.replace(self, **changes)

    # ------------------------------------------------------------------ activations
    def to_raw(self) -> dict:
        """Unconstrained parameters for optimisation (inverse of ``from_raw``)."""
        d = dr.maximum(self.densities, 1e-12)
        # inverse softplus: log(exp(d) - 1) = d + log(1 - exp(-d)). Below 0.1, 1 - exp(-d)
        # cancels (float32: ~1e-4 relative at d = 1e-3, typical trained densities), so use
        # its series to d^5 (truncation < 2e-8 relative there).
        series = d * (1 - d * (1 / 2 - d * (1 / 6 - d * (1 / 24 - d / 120))))
        one_minus = dr.select(d < 0.1, series, 1 - dr.exp(-d))
        raw_d = d + dr.log(one_minus)
        return {"positions": mi.Point3f(self.positions), "raw_scales": dr.log(self.scales),
                "raw_rotations": mi.Vector4f(self.rotations), "raw_densities": raw_d}

    @classmethod
    def from_raw(cls, raw: dict) -> "Gaussians":
        """Physical Gaussians from raw parameters (differentiable; the activations)."""
        x = raw["raw_densities"]
        # softplus(x) = max(x, 0) + log(1 + exp(-|x|)), spelt with selects so that the
        # derivative at x = 0 is 1/2 (dr.abs and dr.maximum give 0 there)
        pos = x > 0
        t = dr.exp(dr.select(pos, -x, x))      # in (0, 1]
        # log(1 + t) = 2 atanh(s), s = t / (2 + t) in (0, 1/3], by its odd series to s^15
        # (truncation < 2e-9 relative). Not dr.log(1 + t): rounding 1 + t costs ~6e-8 / t
        # relative (6e-4 at the t ~ 1e-4 of densities ~ 1e-4), and CUDA's log is accurate
        # only absolutely near 1 (~2e-7: 4e-6 relative at densities ~ 0.05, seen on an H100).
        s = t / (2 + t)
        s2 = s * s
        series = 1 / 13 + s2 * (1 / 15)
        for k in (11, 9, 7, 5, 3, 1):
            series = 1 / k + s2 * series
        softplus = dr.select(pos, x, 0) + 2 * s * series  # stable for all x
        q = raw["raw_rotations"]
        q = q * dr.rsqrt(dr.maximum(dr.squared_norm(q), 1e-24))
        return cls(positions=raw["positions"], scales=dr.exp(raw["raw_scales"]),
                   rotations=q, densities=softplus)

    # ------------------------------------------------------------------ files
    def save_npz(self, path) -> None:
        np.savez(path, **self.numpy())

    @classmethod
    def load_npz(cls, path) -> "Gaussians":
        """The Gaussians of a ``save_npz`` file; GaussiansError naming the file for one
        that is not a complete .npz of valid Gaussians."""
        import zipfile
        import zlib
        names = ("positions", "scales", "rotations", "densities")
        try:
            with np.load(path, allow_pickle=False) as f:
                missing = set(names) - set(getattr(f, "files", ()))
                arrays = None if missing else [f[k] for k in names]
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as e:
            why = "not an .npz archive" if "pickled" in str(e) else f"{e}; truncated?"
            raise GaussiansError(f"{path}: not a readable .npz of Gaussians ({why})") \
                from None
        if missing:
            raise GaussiansError(f"{path}: missing array(s) {sorted(missing)}")
        try:
            return cls.from_numpy(*arrays)
        except (GaussiansError, TypeError, ValueError) as e:
            raise GaussiansError(f"{path}: {e}") from None


def rotation_matrix(q) -> "mi.Matrix3f":
    """Rotation matrix of unit quaternions q = (w, x, y, z) (Dr.Jit, differentiable)."""
    w, x, y, z = q.x, q.y, q.z, q.w   # Vector4f components are named x, y, z, w
    return mi.Matrix3f(
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


def inverse_covariance(scales, rotations) -> "mi.Matrix3f":
    """Sigma^-1 = R diag(1 / s^2) R^T for each Gaussian (Dr.Jit, differentiable)."""
    R = rotation_matrix(rotations)
    w = (1.0 / dr.square(scales.x), 1.0 / dr.square(scales.y), 1.0 / dr.square(scales.z))
    # Entry (i, j) = sum_k R_ik R_jk / s_k^2, written out (symmetric).
    e = [[sum(R[i][k] * R[j][k] * w[k] for k in range(3)) for j in range(3)] for i in range(3)]
    return mi.Matrix3f(e[0][0], e[0][1], e[0][2], e[1][0], e[1][1], e[1][2],
                       e[2][0], e[2][1], e[2][2])


def unit_quaternions(q):
    """q / |q| (differentiable). The projector and the voxelizer normalise with it, so that
    the rotation gradient is tangent to the unit sphere and R(q) is a rotation exactly."""
    return q * dr.rsqrt(dr.squared_norm(q))


def gaussian_checks(g: Gaussians, density_scale=None) -> list:
    """Per-Gaussian validity tests shared by the projector and the voxelizer, in reporting
    order: [(bad lanes, message)]. Lazy; ``first_failure`` evaluates them all at once.
    Widths must already agree (density_scale included)."""
    p, s, q, rho = (dr.detach(a) for a in (g.positions, g.scales, g.rotations, g.densities))

    def nonfinite(*comps):
        bad = ~dr.isfinite(comps[0])
        for c in comps[1:]:
            bad |= ~dr.isfinite(c)
        return bad

    qn = dr.squared_norm(q)
    checks = [
        (nonfinite(p.x, p.y, p.z), "gaussians.positions [N, 3] contains NaN or Inf"),
        (nonfinite(s.x, s.y, s.z), "gaussians.scales [N, 3] contains NaN or Inf"),
        (nonfinite(q.x, q.y, q.z, q.w), "gaussians.rotations [N, 4] (w, x, y, z) contains NaN or Inf"),
        (nonfinite(rho), "gaussians.densities [N] contains NaN or Inf"),
        (dr.minimum(dr.minimum(s.x, s.y), s.z) <= 0,
         "gaussians.scales must be > 0 (standard deviations, length unit)"),
        (rho < 0, "gaussians.densities must be >= 0"),
        (qn == 0, "gaussians.rotations contains a zero quaternion (w, x, y, z)"),
        (dr.abs(dr.sqrt(qn) - 1) > QUATERNION_TOL,
         f"gaussians.rotations must be unit quaternions (w, x, y, z), | |q| - 1 | <= "
         f"{QUATERNION_TOL}; unnormalised quaternions given (normalise them first)"),
    ]
    if density_scale is not None:
        checks.append((nonfinite(dr.detach(density_scale)), "density_scale [N] contains NaN or Inf"))
    return checks


def first_failure(g: Gaussians, checks: list):
    """The message of the first check (in list order) that fails for any Gaussian, or None.

    One kernel and one host synchronisation for all checks (this runs on every training
    iteration): each lane's first failing check index, min-reduced over the lanes. The
    Gaussians' own arrays are evaluated by the same kernel, so later kernels reuse them."""
    code = mi.UInt32(len(checks))
    for k in reversed(range(len(checks))):
        code = dr.select(checks[k][0], k, code)
    dr.schedule(dr.detach(g.positions), dr.detach(g.scales), dr.detach(g.rotations),
                dr.detach(g.densities))
    k = int(dr.min(code)[0])
    return checks[k][1] if k < len(checks) else None
