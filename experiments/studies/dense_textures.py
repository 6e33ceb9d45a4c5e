"""Synthetic dense volumes for confirmation cases: textures that fill the cube like the
micro-CT crops (bone, cement) but that no default was chosen on.

Usage:  .venv/bin/python experiments/studies/dense_textures.py DIR [--n 128] [--seed 0]

Writes into DIR (a folder for ``MI_GRG_DATA``) float32 [x, y, z] cubes in [0, 1] and a
README.md with their provenance, as shared/data's volumes are described:

- ``trabecular_<n>.npy``: the band |f| < t of a smooth Gaussian random field f (white
  noise blurred by a Gaussian of 3 voxels at 128^3), a network of plates and rods like
  trabecular bone, 30 % of the volume, density 1, in a faint marrow of 0.1;
- ``foam_<n>.npy``: a matrix of density 0.6 with pores (0) where a field blurred by 3
  voxels is highest (25 %) and dense grains (1) where a second field is highest (10 %).

Both are blurred by 0.6 voxel so that their edges are not steps on the grid. The seed
picks the noise; every volume is a pure function of (n, seed).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter


def _field(rng, n: int, sigma: float) -> np.ndarray:
    f = gaussian_filter(rng.standard_normal((n, n, n)), sigma * n / 128, mode="wrap")
    return f / f.std()


def trabecular(n: int, seed: int) -> np.ndarray:
    """plates and rods (30 %, density 1) in a faint marrow (0.1), like trabecular bone"""
    f = _field(np.random.default_rng([seed, 1]), n, 3.0)
    t = np.quantile(np.abs(f), 0.30)
    v = np.where(np.abs(f) < t, 1.0, 0.1)
    return np.clip(gaussian_filter(v, 0.6 * n / 128), 0, 1).astype(np.float32)


def foam(n: int, seed: int) -> np.ndarray:
    """a matrix (0.6) with pores (0, 25 %) and dense grains (1, 10 %), like cement"""
    rng = np.random.default_rng([seed, 2])
    pores, grains = _field(rng, n, 3.0), _field(rng, n, 1.5)
    v = np.full((n, n, n), 0.6)
    v[grains > np.quantile(grains, 0.90)] = 1.0
    v[pores > np.quantile(pores, 0.75)] = 0.0
    return np.clip(gaussian_filter(v, 0.6 * n / 128), 0, 1).astype(np.float32)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("dir", type=Path)
    p.add_argument("--n", type=int, default=128)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    a.dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, make in (("trabecular", trabecular), ("foam", foam)):
        f = f"{name}_{a.n}.npy"
        np.save(a.dir / f, make(a.n, a.seed))
        rows.append(f"| {f} | {make.__doc__ or name} | experiments/studies/dense_textures.py "
                    f"--n {a.n} --seed {a.seed} | the project's (generated) |")
    (a.dir / "README.md").write_text(
        "# Synthetic dense volumes (experiments/studies/dense_textures.py)\n\n"
        "| file | what | source | licence |\n|---|---|---|---|\n" + "\n".join(rows) + "\n")
    print(f"wrote {', '.join(r.split(' | ')[0][2:] for r in rows)} into {a.dir}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
