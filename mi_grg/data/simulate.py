"""Simulated CT cases from analytic phantoms: exact projections, optional noise, ground truth.

The default scanner is R2-Gaussian's synthetic one (``cone_beam.yml``: DSD 7, DSO 5,
volume 2^3 centred at the origin) at a smaller resolution. Its detector is widened so that
the whole shadow of the volume box, corners included, falls on it: R2-Gaussian's 4.0 misses
the corners in cone beam (their shadow spans 4.13 in u), and its parallel-beam 2.0 misses
everything beyond |u| = 1 (the box's diagonal spans 2 sqrt 2). We use 4.2 (cone) and 3.0
(parallel); both give a pixel footprint at the rotation axis of 3 / nDetector.

Nothing here writes files: ``save_case`` / ``load_case`` do.
"""
from __future__ import annotations

import numpy as np

from mi_grg.data.case import Case
from mi_grg.core.geometry import Geometry, circular_angles
from mi_grg.data.noise import NoiseModel
from mi_grg.data.phantoms import EllipsoidPhantom, make_phantom

DSD, DSO, SVOXEL = 7.0, 5.0, 2.0
SDETECTOR = {"cone": 4.2, "parallel": 3.0}


def default_geometry(n: int = 64, det: int = 96, views: int = 25, mode: str = "cone") -> Geometry:
    """R2-Gaussian's synthetic scanner with an ``n^3`` volume of size 2 (normalised units),
    a ``det x det`` detector of size ``SDETECTOR[mode]`` and ``views`` training angles
    ``circular_angles(views)`` (0..2 pi, endpoint excluded, radians)."""
    if mode not in SDETECTOR:
        raise ValueError(f"mode must be one of {tuple(SDETECTOR)}, got {mode!r}")
    s = SDETECTOR[mode]
    return Geometry(mode=mode, DSD=DSD, DSO=DSO, nDetector=(det, det), sDetector=(s, s),
                    nVoxel=(n, n, n), sVoxel=(SVOXEL,) * 3, angles=circular_angles(views))


def default_test_angles(n: int) -> np.ndarray:
    """``n`` test angles (radians) offset by half a step from ``circular_angles(n)``, so that
    with as many test as training views each test view lies midway between two."""
    return circular_angles(n) + np.pi / int(n)


def simulate_case(phantom, geometry: Geometry, test_angles=None, noise: NoiseModel | None = None,
                  seed: int = 0, supersample: int = 4, noise_seed: int | None = None) -> Case:
    """A simulated case in file units (``scene_scale = 1``).

    Args:
        phantom:     a name in ``PHANTOMS`` (built with ``make_phantom(name, seed)``) or an
                     ``EllipsoidPhantom``.
        geometry:    scan geometry; its angles are the training angles.
        test_angles: test angles (radians); None -> ``default_test_angles(n_train_views)``;
                     an empty array gives no test views (``test`` of shape [0, v, u]).
        noise:       ``NoiseModel`` applied to the training views only (None: exact).
        seed:        phantom seed (random families), and the noise seed unless
                     ``noise_seed`` is given.
        supersample: sub-voxel points per axis for the ground-truth volume.
        noise_seed:  the noise draws from ``np.random.default_rng([noise_seed, 1])``, a
                     stream apart from the phantom's (a scene file's ``noise_seed``).
    Returns:
        Case with float32 ``train`` [view, v, u] (exact line integrals, plus noise), ``test``
        [view, v, u] (exact, noise-free), ``vol_gt`` [x, y, z] and ``info``.
    """
    if not isinstance(geometry, Geometry):
        raise TypeError(f"geometry must be a mi_grg.Geometry, got {type(geometry).__name__}")
    if noise is not None and not isinstance(noise, NoiseModel):
        raise TypeError(f"noise must be a NoiseModel or None, got {type(noise).__name__}")
    seed = int(seed)
    noise_seed = seed if noise_seed is None else int(noise_seed)
    if seed < 0 or noise_seed < 0:
        raise ValueError(f"seed and noise_seed must be >= 0, got {seed}, {noise_seed}")
    if isinstance(phantom, str):
        phantom = make_phantom(phantom, seed=seed)
    elif not isinstance(phantom, EllipsoidPhantom):
        raise TypeError(f"phantom must be a name or an EllipsoidPhantom, got "
                        f"{type(phantom).__name__}")
    train, test, test_angles = simulated_views(phantom.line_integrals, geometry, test_angles,
                                               noise, noise_seed)
    vol = phantom.voxelize(geometry, supersample=supersample)
    info = {
        "source": "mi_grg.data.simulate",
        "phantom": phantom.name,
        "n_ellipsoids": len(phantom),
        "noise": None if noise is None else noise.to_dict(),
        "seed": seed,
        "noise_seed": noise_seed,
        "supersample": int(supersample),
        **scan_fields(geometry, test_angles),
    }
    return Case(geometry=geometry, train=train, test_angles=test_angles, test=test, vol_gt=vol,
                scene_scale=1.0, info=info)


def simulated_views(project, geometry: Geometry, test_angles, noise: NoiseModel | None,
                    noise_seed: int):
    """(train, test, test_angles) of a simulation: ``project(geometry[, angles])`` gives
    exact line integrals [view, v, u]; noise (``np.random.default_rng([noise_seed, 1])``)
    goes on the training views only; test_angles None -> ``default_test_angles``, empty ->
    test of shape [0, v, u]. Projections float32, angles float64 radians."""
    if test_angles is None:
        test_angles = default_test_angles(geometry.n_views)
    test_angles = np.asarray(test_angles, np.float64).reshape(-1)
    if not np.all(np.isfinite(test_angles)):
        raise ValueError("test_angles must be finite (radians)")
    train = project(geometry)
    if noise is not None:
        train = noise.apply(train, np.random.default_rng([noise_seed, 1]))
    if test_angles.size:
        test = np.asarray(project(geometry, test_angles), np.float32)
    else:
        test = np.zeros((0, *geometry.nDetector), np.float32)
    return np.asarray(train, np.float32), test, test_angles


def scan_fields(geometry: Geometry, test_angles) -> dict:
    """The scan's sizes as a simulated case's ``info`` records them."""
    return {"mode": geometry.mode, "n_voxel": list(geometry.nVoxel),
            "n_detector": list(geometry.nDetector), "n_train": geometry.n_views,
            "n_test": int(np.size(test_angles))}


def check_simulation_memory(geometry: Geometry, n_test: int, where: str) -> None:
    """Refuse (one line naming the sizes and --max-memory) a simulation whose ground truth
    (float64 while voxelised, then float32) and projections (float64, then float32) would
    not fit (``mi_grg.core.memory``)."""
    from mi_grg.core import memory
    memory.check([memory.volume(geometry.nVoxel, copies=3, what="ground truth"),
                  memory.projections(geometry.n_views + int(n_test), geometry.nDetector,
                                     copies=4)],
                 where, lower="lower nVoxel, nDetector or the number of views")
