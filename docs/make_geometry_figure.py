"""Draw docs/img/geometry.png: the scan geometry of docs/conventions.md.

Run: ``.venv/bin/python docs/make_geometry_figure.py``. Positions come from
``Geometry.detector_frame`` and ``Geometry.rays`` so the picture shows what the code does.
"""
from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Arc, Rectangle  # noqa: E402

from mi_grg.core.geometry import Geometry  # noqa: E402

A = math.radians(35)  # the drawn view angle
GEO = Geometry(mode="cone", DSD=7.0, DSO=5.0, nDetector=(8, 8), sDetector=(4.2, 4.2),
               nVoxel=(8, 8, 8), sVoxel=(2.0, 2.0, 2.0), angles=[A])
PIXEL = (1, 6)  # (v, u) index of the drawn ray's pixel


def _arrow(ax, p, d, text, color, offset=(0.15, 0.15)):
    ax.annotate("", xy=(p[0] + d[0], p[1] + d[1]), xytext=(p[0], p[1]),
                arrowprops=dict(arrowstyle="->", color=color, lw=2))
    ax.text(p[0] + d[0] + offset[0], p[1] + d[1] + offset[1], text, color=color, fontsize=11,
            bbox=dict(fc="w", ec="none", alpha=0.8, pad=1))


def top_view(ax):
    f = {k: v[0] for k, v in GEO.detector_frame().items()}
    src, cen, eu, n = f["source"], f["center"], f["e_u"], f["normal"]
    half = GEO.sDetector[1] / 2
    # volume box and world axes
    ax.add_patch(Rectangle((-1, -1), 2, 2, fill=True, color="0.9", ec="0.4"))
    ax.text(-0.95, 0.8, "volume\n(sVoxel)", fontsize=8, color="0.3")
    _arrow(ax, (0, 0), (1.6, 0), "x", "k", (0.05, -0.35))
    _arrow(ax, (0, 0), (0, 1.6), "y", "k", (-0.35, 0.0))
    ax.plot(0, 0, "ko", ms=7, mfc="w")
    ax.plot(0, 0, "k.", ms=3)
    ax.text(-0.2, -1.45, "z: rotation axis\n(out of page)", fontsize=8)
    # source, detector, e_u
    ax.plot(*src[:2], "r*", ms=16)
    ax.text(src[0] + 0.2, src[1], "source\n(DSO cos a, DSO sin a, 0)", color="r", fontsize=9)
    ends = np.array([cen - half * eu, cen + half * eu])
    ax.plot(ends[:, 0], ends[:, 1], "b-", lw=5, solid_capstyle="butt")
    ax.text(ends[0][0] - 0.6, ends[0][1] - 0.65, "detector (u: column index)", color="b",
            fontsize=9)
    _arrow(ax, ends[0][:2] - 0.45 * n[:2], 1.2 * eu[:2], "e_u = (-sin a, cos a, 0)", "b",
           (-3.3, 0.05))
    # a ray from the source through a pixel centre
    o, d, length = GEO.rays(np.cos(A), np.sin(A), PIXEL[0] + 0.5, PIXEL[1] + 0.5)
    o, d = np.array(o, float), np.array(d, float)
    p = o + float(length) * d
    ax.plot([o[0], p[0]], [o[1], p[1]], "g-", lw=1.5)
    ax.text(*(o + 0.55 * float(length) * d)[:2] + np.array([0.1, 0.15]), "ray", color="g")
    # central ray and the angle a
    ax.plot([src[0], cen[0]], [src[1], cen[1]], "k:", lw=1)
    ax.add_patch(Arc((0, 0), 3.2, 3.2, theta1=0, theta2=math.degrees(A), color="m", lw=1.5))
    ax.text(1.75 * math.cos(A / 2), 1.75 * math.sin(A / 2), "a", color="m", fontsize=13)
    ax.set_title("top view (z towards the viewer)")
    ax.set_xlabel("x")
    ax.set_ylabel("y")


def side_view(ax):
    # the plane of the central ray and z: horizontal = position along n = (cos a, sin a, 0)
    half_v = GEO.sDetector[0] / 2
    back = -(GEO.DSD - GEO.DSO)
    ax.add_patch(Rectangle((-1, -1), 2, 2, fill=True, color="0.9", ec="0.4"))
    ax.plot(GEO.DSO, 0, "r*", ms=16)
    ax.text(GEO.DSO - 0.4, 0.35, "source", color="r", fontsize=9)
    ax.plot([back, back], [-half_v, half_v], "b-", lw=5, solid_capstyle="butt")
    ax.text(back + 0.2, half_v - 0.1, "detector\n(v: row index)", color="b", fontsize=9)
    _arrow(ax, (back - 0.35, half_v), (0, -1.2), "e_v = (0, 0, -1)", "b", (-1.6, -0.45))
    ax.plot([0, 0], [-2.6, 2.6], "k-.", lw=1)
    ax.text(0.08, 2.3, "rotation axis z", fontsize=8)
    _arrow(ax, (0, 0), (0, 1.4), "z", "k", (0.1, -0.2))
    # the drawn pixel row: its z is -(v + 0.5 - nv/2) dv
    dv = GEO.dDetector[0]
    z = -(PIXEL[0] + 0.5 - GEO.nDetector[0] / 2) * dv
    ax.plot([GEO.DSO, back], [0, z], "g-", lw=1.5)
    ax.text(1.5, 0.6, "ray", color="g")
    ax.plot([GEO.DSO, back], [0, 0], "k:", lw=1)
    ax.annotate("", xy=(0, -2.3), xytext=(GEO.DSO, -2.3),
                arrowprops=dict(arrowstyle="<->", color="k"))
    ax.text(GEO.DSO / 2 - 0.3, -2.2, "DSO", fontsize=9)
    ax.annotate("", xy=(back, -2.75), xytext=(GEO.DSO, -2.75),
                arrowprops=dict(arrowstyle="<->", color="k"))
    ax.text(-0.9, -2.65, "DSD", fontsize=9)
    ax.text(-0.95, 0.75, "volume", fontsize=8, color="0.3")
    ax.set_title("side view (plane of the central ray and z)")
    ax.set_xlabel("position along (cos a, sin a, 0)")
    ax.set_ylabel("z")


def main(out=Path(__file__).resolve().parent / "img" / "geometry.png"):
    fig, axes = plt.subplots(1, 2, figsize=(13, 6.2))
    top_view(axes[0])
    side_view(axes[1])
    for ax in axes:
        ax.set_aspect("equal")
        ax.grid(alpha=0.2)
    axes[0].set_xlim(-4.2, 7.2)
    axes[0].set_ylim(-3.6, 5.2)
    axes[1].set_xlim(-2.8, 6.0)
    axes[1].set_ylim(-3.0, 2.8)
    fig.suptitle("mi_grg scan geometry (R2-Gaussian / TIGRE conventions); a = 35 degrees",
                 fontsize=12)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
