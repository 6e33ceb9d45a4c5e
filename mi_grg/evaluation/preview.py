"""A 3-D preview of a reconstructed volume, rendered by Mitsuba.

``mi-grg render --run OUT --preview`` renders ``OUT/vol_pred.npy`` (any method: gr / r2
runs write the voxelised Gaussians there too) as an emission-absorption volume: a small
Mitsuba integrator marches each camera ray through the grid (trilinear ``mi.Texture3f``),
and a transfer function maps density to colour and opacity. Cameras orbit the rotation
axis (+z up) at a fixed elevation; it writes ``preview.png`` (a contact sheet of a few
azimuths) and ``preview.gif`` (the full orbit).

The transfer function is read off the volume's histogram, no hand tuning: with ``hi`` the
99.5th percentile of the positive voxels (a robust maximum) and ``lo`` the median of the
voxels above ``hi / 10`` (the bulk of the object, not its background noise), densities
below ``lo`` are transparent, opacity and colour rise linearly to ``hi``: what is denser
than the bulk shows. Opacity is scaled so that a ray along the box's longest side through
density ``hi`` has optical depth ``OPTICAL_DEPTH``: thin dense shells stay see-through.
A volume that is not finite or has no positive voxel is a ValueError, not a black image.
"""
from __future__ import annotations

import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

#: Azimuths of the animated orbit; the contact sheet shows every ``SHEET_STEP``-th one.
N_VIEWS = 24
SHEET_STEP = 3
#: Rendered image side (pixels), camera elevation above the z = 0 plane (degrees).
SIZE = 256
ELEVATION_DEG = 20.0
#: Ray-marching step in voxels; samples per pixel (jittered: no wood-grain bands).
STEP_VOXELS = 0.5
SPP = 4
#: The largest --spp: every sample of every view is one lane of a single pass.
MAX_SPP = 256
#: Optical depth of a ray crossing the box's longest side through density ``hi``.
OPTICAL_DEPTH = 12.0
#: Colour map of the emission (matplotlib name), from its ``CMAP_START`` on.
CMAP, CMAP_START = "inferno", 0.2
#: Entries of the colour/opacity lookup table.
LUT_SIZE = 256
PREVIEW_PNG, PREVIEW_GIF = "preview.png", "preview.gif"


def transfer_function(vol: np.ndarray) -> dict:
    """Breakpoints ``lo`` = ``start`` and ``hi`` (densities) of ``vol`` [x, y, z], and the
    RGBA lookup table [LUT_SIZE, 4] over x = (density - start) / (hi - start) in [0, 1]:
    colour in [0, 1], opacity as a fraction of the maximum extinction. ValueError for a
    volume that is not finite or has nothing positive to show."""
    vol = np.asarray(vol)
    bad = int(np.size(vol) - np.count_nonzero(np.isfinite(vol)))
    if bad:
        raise ValueError(f"the volume has {bad} non-finite voxel(s) (NaN/Inf); no preview "
                         "drawn")
    pos = vol[vol > 0]
    if pos.size == 0:
        what = "all zero" if not np.any(vol) else f"never positive (max {float(vol.max()):.3g})"
        raise ValueError(f"the volume is {what}: nothing to preview")
    hi = float(np.percentile(pos, 99.5))
    bulk = pos[pos > hi / 10]
    lo = float(np.median(bulk))
    if not hi > lo:   # a uniform object: ramp from 0
        lo = 0.0
    import matplotlib
    x = np.linspace(0.0, 1.0, LUT_SIZE)
    rgb = matplotlib.colormaps[CMAP](CMAP_START + (1 - CMAP_START) * x)[:, :3]
    lut = np.concatenate([rgb, x[:, None]], axis=1).astype(np.float32)
    return {"lo": lo, "hi": hi, "start": lo, "lut": lut,
            "rule": "lo = median of voxels > hi / 10 (0 if that is hi), hi = 99.5th "
                    "percentile of positive voxels; opacity and colour linear from lo to hi"}


_CLASSES: dict = {}


def _integrator_class():
    """The emission-absorption integrator, defined against the active variant (Python
    plugin classes bind to the variant active when they are defined)."""
    if mi.variant() in _CLASSES:
        return _CLASSES[mi.variant()]

    class EmissionAbsorption(mi.SamplingIntegrator):
        """Front-to-back compositing along each ray; returns (luminance, valid, [r, g, b,
        alpha]) with premultiplied colour on a black background."""

        def __init__(self, props, volume, box, step, sigma_max, start, hi, lut):
            super().__init__(props)
            self.volume = mi.Texture3f(mi.TensorXf(volume))     # [z, y, x, 1]
            self.lut = mi.Texture1f(mi.TensorXf(lut))           # [LUT_SIZE, 4]
            self.bmin, self.bmax = mi.ScalarPoint3f(box[0]), mi.ScalarPoint3f(box[1])
            self.step, self.sigma_max = float(step), float(sigma_max)
            self.start, self.inv_range = float(start), 1.0 / float(hi - start)
            # x = 0 and 1 land on the first and last texel centres
            n = lut.shape[0]
            self.lut_scale, self.lut_offset = (n - 1) / n, 0.5 / n

        def aov_names(self):
            return ["r", "g", "b", "a"]

        @dr.syntax
        def sample(self, scene, sampler, ray, medium=None, active=True):
            o, d = mi.Point3f(ray.o), mi.Vector3f(ray.d)
            t0 = (mi.Point3f(self.bmin) - o) / d
            t1 = (mi.Point3f(self.bmax) - o) / d
            t_near = dr.maximum(dr.max(dr.minimum(t0, t1)), 0.0)
            t_far = dr.min(dr.maximum(t0, t1))
            t = t_near + self.step * sampler.next_1d()
            size = mi.Vector3f(self.bmax) - mi.Vector3f(self.bmin)
            trans, r, g, b = mi.Float(1.0), mi.Float(0.0), mi.Float(0.0), mi.Float(0.0)
            alive = mi.Bool(active) & (t_far > t_near)
            while alive & (t < t_far) & (trans > 1e-3):
                uvw = (o + d * t - mi.Point3f(self.bmin)) / size
                dens = self.volume.eval(mi.Point3f(uvw))[0]
                x = dr.clip((dens - self.start) * self.inv_range, 0.0, 1.0)
                c = self.lut.eval(mi.Point1f(x * self.lut_scale + self.lut_offset))
                alpha = 1.0 - dr.exp(-c[3] * self.sigma_max * self.step)
                w = trans * alpha
                r, g, b = r + w * c[0], g + w * c[1], b + w * c[2]
                trans = trans * (1.0 - alpha)
                t += self.step
            a = 1.0 - trans
            lum = 0.2126 * r + 0.7152 * g + 0.0722 * b
            return mi.Spectrum(lum), mi.Bool(True), [r, g, b, a]

    _CLASSES[mi.variant()] = EmissionAbsorption
    return EmissionAbsorption


def _framing(vol: np.ndarray, start: float, box_size: np.ndarray) -> tuple:
    """(centre, radius) in box coordinates of a sphere around the visible voxels (above
    ``start``), robust to a few stray noise voxels: their middle 99.6 % per axis, the
    99.5th percentile of their distances from its centre."""
    idx = np.argwhere(vol > start)
    if len(idx) == 0:
        return np.zeros(3), 0.5 * float(np.linalg.norm(box_size))
    pos = ((idx + 0.5) / np.asarray(vol.shape) - 0.5) * box_size
    lo, hi = np.percentile(pos, 0.2, axis=0), np.percentile(pos, 99.8, axis=0)
    centre = (lo + hi) / 2
    voxel = float(np.max(box_size / np.asarray(vol.shape)))
    radius = float(np.percentile(np.linalg.norm(pos - centre, axis=1), 99.5)) + voxel
    return centre, radius


def _camera_dicts(centre, radius: float, n_views: int, size: int,
                  elevation_deg: float) -> list:
    """Perspective cameras orbiting the z axis through ``centre``, a sphere of ``radius``
    there filling the frame; image up = +z, azimuth 2 pi k / n_views (k = 0: from +x)."""
    dist = 3.0 * radius
    fov = 2.0 * np.degrees(np.arcsin(radius / dist)) * 1.02
    e = np.radians(elevation_deg)
    c = np.asarray(centre, np.float64)
    cams = []
    for k in range(n_views):
        a = 2.0 * np.pi * k / n_views
        eye = c + dist * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        cams.append({"type": "perspective", "fov": float(fov), "fov_axis": "x",
                     "to_world": mi.ScalarTransform4f().look_at(
                         origin=eye.tolist(), target=c.tolist(), up=[0, 0, 1]),
                     # the batch sensor's film is the one rendered; this one is unused
                     "film": {"type": "hdrfilm", "width": size, "height": size,
                              "pixel_format": "luminance"}})
    return cams


def render_views(vol: np.ndarray, spacing=(1.0, 1.0, 1.0), n_views: int = N_VIEWS,
                 size: int = SIZE, elevation_deg: float = ELEVATION_DEG, spp: int = SPP,
                 tf: dict | None = None, framing: tuple | None = None) -> np.ndarray:
    """Render ``vol`` [x, y, z] (voxel size ``spacing`` [x, y, z], any unit) from
    ``n_views`` azimuths; returns premultiplied RGBA images [view, row, column, 4]
    (row 0 at the top, +z up on screen). One Mitsuba ``batch`` sensor renders every view
    in one pass. ``framing``: (centre, radius) of the sphere the cameras frame, in box
    coordinates (longest side 1, centred at 0); default: around the visible voxels."""
    from mi_grg.core import memory
    memory.check([memory.film(n_views, (size, size), spp, max_lanes=memory.MAX_ENTRIES),
                  memory.volume(vol.shape, copies=3)], "render --preview",
                 lower="lower --spp")
    vol = np.asarray(vol, np.float32)
    tf = transfer_function(vol) if tf is None else tf
    extent = np.asarray(vol.shape, np.float64) * np.asarray(spacing, np.float64)
    box_size = extent / extent.max()                    # longest side 1, centred at 0
    step = STEP_VOXELS * float(np.min(box_size / np.asarray(vol.shape)))
    sigma_max = OPTICAL_DEPTH                           # per unit length = longest side
    cls = _integrator_class()
    integ = cls(mi.Properties(), vol.transpose(2, 1, 0)[..., None].copy(),
                (-box_size / 2, box_size / 2), step, sigma_max, tf["start"], tf["hi"],
                tf["lut"])
    sensor = {"type": "batch",
              "film": {"type": "hdrfilm", "width": size * n_views, "height": size,
                       "pixel_format": "luminance", "rfilter": {"type": "box"}},
              "sampler": {"type": "independent", "sample_count": spp}}
    framing = _framing(vol, tf["start"], box_size) if framing is None else framing
    cams = _camera_dicts(*framing, n_views, size, elevation_deg)
    for k, cam in enumerate(cams):
        sensor[f"view{k:03d}"] = cam
    scene = mi.load_dict({"type": "scene", "sensor": sensor})
    img = np.array(mi.render(scene, integrator=integ, spp=spp))   # [row, view*col, 5]
    rgba = img[:, :, 1:5].reshape(size, n_views, size, 4).transpose(1, 0, 2, 3)
    return np.clip(rgba, 0.0, 1.0)


def load_run_volume(run_dir) -> tuple:
    """(volume [x, y, z], spacing [x, y, z], unit, method) of a finished run: its
    vol_pred.npy (or vol_pred.tif) and the voxel size of its metrics.json."""
    import json
    run = Path(run_dir)
    npy, tif = run / "vol_pred.npy", run / "vol_pred.tif"
    if npy.is_file():
        vol = np.load(npy)
    elif tif.is_file():
        import tifffile
        vol = tifffile.imread(tif).transpose(2, 1, 0)      # ZYX pages -> [x, y, z]
    else:
        raise FileNotFoundError(f"{npy} not found (nor {tif.name}): --preview needs a "
                                "finished run's volume (mi-grg reconstruct --out DIR)")
    if vol.ndim != 3:
        raise ValueError(f"{npy if npy.is_file() else tif}: expected a 3-D volume [x, y, z], "
                         f"got shape {vol.shape}")
    spacing, unit, method = (1.0, 1.0, 1.0), "voxel", run.name
    try:
        m = json.loads((run / "metrics.json").read_text())
    except (OSError, ValueError):
        m = None
    if m and "geometry" in m:
        from mi_grg.data.export import voxel_grid
        spacing = voxel_grid(m["geometry"])["spacing"]
        unit = str(((m.get("data") or {}).get("units") or {}).get("length", "normalised"))
        method = m.get("method", method)
    return vol, spacing, unit, method


def _to_uint8(rgba: np.ndarray) -> np.ndarray:
    """Premultiplied RGBA [view, row, col, 4] on black -> uint8 RGB, one exposure for all
    views: the 99.9th percentile of the object's brightest channel maps to white."""
    rgb = rgba[..., :3]
    seen = rgba[..., 3] > 1e-2
    peak = float(np.percentile(rgb.max(-1)[seen], 99.9)) if np.any(seen) else 1.0
    return (np.clip(rgb / max(peak, 1e-6), 0.0, 1.0) * 255 + 0.5).astype(np.uint8)


def _contact_sheet(path, frames: np.ndarray, tf: dict, title: str, unit: str,
                   n_views: int) -> None:
    """Every SHEET_STEP-th frame [view, row, col, 3] with its azimuth, and the transfer
    function's colour bar in density units."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    picks = list(range(0, n_views, SHEET_STEP)) if n_views > SHEET_STEP else list(range(n_views))
    cols = min(4, len(picks))
    rows = -(-len(picks) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(2.4 * cols, 2.4 * rows + 0.9),
                             squeeze=False, facecolor="black",
                             gridspec_kw={"wspace": 0.02, "hspace": 0.12})
    for ax in axes.ravel():
        ax.set_axis_off()
    for ax, k in zip(axes.ravel(), picks):
        ax.imshow(frames[k])
        ax.set_title(f"azimuth {360.0 * k / n_views:.0f} deg", color="white", fontsize=8)
    sm = plt.cm.ScalarMappable(cmap=matplotlib.colors.ListedColormap(tf["lut"][:, :3]),
                               norm=matplotlib.colors.Normalize(tf["start"], tf["hi"]))
    cb = fig.colorbar(sm, ax=axes.ravel().tolist(), orientation="horizontal", shrink=0.6,
                      fraction=0.05, pad=0.02)
    per = "normalised" if unit == "normalised" else f"1/{unit}"
    cb.set_label(f"density ({per}): transparent below, opacity rising to the right",
                 color="white", fontsize=8)
    cb.ax.tick_params(colors="white", labelsize=7)
    fig.suptitle(title, color="white", fontsize=9)
    fig.savefig(path, dpi=100, facecolor="black")
    plt.close(fig)


def write_preview(run_dir, out_dir=None, n_views: int = N_VIEWS, size: int = SIZE,
                  spp: int = SPP) -> dict:
    """Render a run's volume and write ``preview.png`` (contact sheet) and ``preview.gif``
    (the orbit) into ``out_dir`` (default: the run's directory). Returns the paths, the
    transfer function's breakpoints and the seconds taken."""
    from PIL import Image
    t0 = time.perf_counter()
    vol, spacing, unit, method = load_run_volume(run_dir)
    tf = transfer_function(vol)
    rgba = render_views(vol, spacing, n_views=n_views, size=size, spp=spp, tf=tf)
    frames = _to_uint8(rgba)
    out = Path(run_dir if out_dir is None else out_dir)
    out.mkdir(parents=True, exist_ok=True)
    title = (f"{method}: {'x'.join(map(str, vol.shape))} voxels, emission-absorption, "
             f"+z up, {ELEVATION_DEG:g} deg elevation")
    _contact_sheet(out / PREVIEW_PNG, frames, tf, title, unit, n_views)
    images = [Image.fromarray(f) for f in frames]
    images[0].save(out / PREVIEW_GIF, save_all=True, append_images=images[1:],
                   duration=int(4000 / n_views), loop=0)
    return {"png": out / PREVIEW_PNG, "gif": out / PREVIEW_GIF, "lo": tf["start"],
            "hi": tf["hi"], "unit": unit, "views": n_views,
            "seconds": time.perf_counter() - t0}


def preview_command(args) -> int:
    """``mi-grg render --run OUT --preview [--out DIR] [--spp N]``: checks the flags, writes
    the preview, prints where. ValueError / FileNotFoundError for bad input (the CLI prints
    them in one line)."""
    if args.run is None or args.scene is not None:
        raise ValueError("--preview renders a finished run's volume: give --run OUT_DIR "
                         "and no scene file")
    extra = [f for f, v in (("--views", args.views), ("--det", args.det),
                            ("--data", args.data)) if v is not None]
    if extra:
        raise ValueError(f"{', '.join(extra)} only apply to the path-traced cross-check, not "
                         "to --preview")
    spp = SPP if args.spp is None else int(args.spp)
    if not 1 <= spp <= MAX_SPP:
        raise ValueError(f"--spp {spp}: expected 1 to {MAX_SPP}")
    from mi_grg.data import outputs
    if args.out is None:     # beside the run's files: each of the two replaced whole
        with outputs.staged_files(args.run, (PREVIEW_PNG, PREVIEW_GIF), "preview") as tmp:
            res = write_preview(args.run, tmp, spp=spp)
    else:                    # a folder of its own: the one rule of every --out
        outputs.check_out(args.out, outputs.PREVIEW, [args.run])
        with outputs.staged(args.out, outputs.PREVIEW) as tmp:
            res = write_preview(args.run, tmp, spp=spp)
    shown = Path(args.run if args.out is None else args.out)
    print(f"preview of {args.run}: {res['views']} azimuths, density {res['lo']:.4g} to "
          f"{res['hi']:.4g} ({res['unit']}) from the histogram, {res['seconds']:.1f} s  -> "
          f"{shown / PREVIEW_PNG}, {shown / PREVIEW_GIF}")
    return 0
