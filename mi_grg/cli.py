"""``mi-grg``: simulate, reconstruct, render (path-traced cross-check), experiment suites and
their report, and demo."""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
import zipfile
from pathlib import Path

from mi_grg.data.inputs import MAX_MESSAGE, describe_error, one_line  # noqa: F401  (public)


def _parse_options(items) -> dict:
    """``key=value`` pairs; values parsed as JSON where possible (numbers, true/false)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"--option {item!r}: expected KEY=VALUE (e.g. n_iter=20)")
        key, value = item.split("=", 1)
        try:
            out[key.replace("-", "_")] = json.loads(value)
        except json.JSONDecodeError:
            out[key.replace("-", "_")] = value
    return out


def _raw_options(items) -> dict:
    """``key=value`` pairs as given (for messages)."""
    return {k.replace("-", "_"): v for k, v in (i.split("=", 1) for i in items or [])}


#: The data set's copy of the scan it simulated (load it with ``simulate --scene``).
SCENE_XML = "scene.xml"

#: simulate's flags that a scene file states itself: attribute -> (flag, where in the scene).
#: With --scene they are errors, so that the data never differ from what the file says.
_SCENE_FIELDS = {
    "phantom": ("--phantom", '<string name="phantom"> of <medium type="ct_phantom">'),
    "seed": ("--seed", '<integer name="seed"> of <medium type="ct_phantom"> (random '
                       'phantoms) and <integer name="noise_seed"> of the ct_scanner'),
    "n": ("--n", 'nVoxel of <sensor type="ct_scanner">'),
    "det": ("--det", 'nDetector of <sensor type="ct_scanner">'),
    "mode": ("--mode", 'mode of <sensor type="ct_scanner">'),
    "no_noise": ("--no-noise", 'noise="none" of <sensor type="ct_scanner">'),
    "I0": ("--I0", 'I0 of <sensor type="ct_scanner"> (with noise="poisson+gaussian")'),
    "electronic_std": ("--electronic-std", 'electronic_std of <sensor type="ct_scanner"> '
                                           '(with noise="poisson+gaussian")'),
}


def _refuse_scene_conflicts(args) -> None:
    """SystemExit naming every flag given together with --scene that the scene states."""
    given = [k for k in _SCENE_FIELDS if getattr(args, k, None) is not None]
    if given:
        where = "; ".join(f"{_SCENE_FIELDS[k][0]} -> {_SCENE_FIELDS[k][1]}" for k in given)
        raise SystemExit(f"{', '.join(_SCENE_FIELDS[k][0] for k in given)} cannot be combined "
                         f"with --scene {args.scene}: the scene file states "
                         f"{'it' if len(given) == 1 else 'them'} ({where}). Edit the scene "
                         "file instead (or leave out --scene).")


def _check_simulable(scan, path) -> None:
    """simulate computes exact line integrals of an analytic phantom; refuse a scene that
    asks for anything else rather than leave part of it silently unused."""
    from mi_grg.data.scene import tag_of
    unused = [f"<{tag_of(o['type'], 'object')} type=\"{o['type']}\">"
              for o in ([scan.integrator] if scan.integrator else []) + list(scan.other)]
    if unused:
        raise SystemExit(
            f"{path} declares {', '.join(unused)}, which `mi-grg simulate` would not use: it "
            "computes exact closed-form line integrals of the phantom. Render this scene with "
            f"`mi-grg render {path} --out DIR`, or remove them from the scene to simulate it.")
    kind = scan.object.get("type")
    if kind != "ct_phantom":
        raise SystemExit(f"{path}: `mi-grg simulate` needs <medium type=\"ct_phantom\"> inside "
                         f"the ct_scanner sensor (an analytic phantom), got "
                         f"{'no medium' if kind is None else repr(kind)}")


def _default_scan(args):
    """The scan that the flags describe (no --scene), as a ``Scan`` and the seed."""
    import numpy as np
    from mi_grg.data.scene import DEFAULT_ELECTRONIC_STD, DEFAULT_I0, Scan
    from mi_grg.data.simulate import default_geometry, default_test_angles

    noise_flags = [f for k, f in (("I0", "--I0"), ("electronic_std", "--electronic-std"))
                   if getattr(args, k) is not None]
    if args.no_noise and noise_flags:
        raise SystemExit(f"{' and '.join(noise_flags)} set the noise model, which --no-noise "
                         "turns off; give one or the other")
    geometry = default_geometry(n=64 if args.n is None else args.n,
                                det=96 if args.det is None else args.det,
                                views=25 if args.views is None else args.views,
                                mode=args.mode or "cone")
    test_views = 25 if args.test_views is None else args.test_views
    test_angles = default_test_angles(test_views) if test_views else np.zeros(0)
    phantom = args.phantom or "shepp"
    seed = 0 if args.seed is None else args.seed
    noise = None if args.no_noise else {
        "model": "poisson+gaussian",
        "I0": DEFAULT_I0 if args.I0 is None else float(args.I0),
        "electronic_std": (DEFAULT_ELECTRONIC_STD if args.electronic_std is None
                           else float(args.electronic_std)),
        "seed": int(seed), "clip_negative": True}
    obj = {"type": "ct_phantom", "phantom": phantom}
    if phantom != "shepp":          # ct_phantom refuses a seed for the fixed Shepp-Logan head
        obj["seed"] = int(seed)
    return Scan(geometry=geometry, test_angles=test_angles, noise=noise, object=obj), seed


def cmd_simulate(args) -> int:
    from mi_grg.data import outputs
    from mi_grg.data.dataset import save_case
    from mi_grg.data.noise import NoiseModel
    from mi_grg.data.scene import load_scan, scan_to_xml
    from mi_grg.data.simulate import check_simulation_memory, simulate_case

    outputs.check_out(args.out, outputs.SIMULATE, [args.scene])
    if args.scene:
        _refuse_scene_conflicts(args)
        # --views / --test-views are overrides that load_scan applies to the scan itself, so
        # they reach the data set's scene.xml and metrics like any scene field.
        overrides = {k: v for k, v in (("views", args.views), ("test_views", args.test_views))
                     if v is not None}
        scan = load_scan(args.scene, overrides or None)
        _check_simulable(scan, args.scene)
        seed = int(scan.object.get("seed", 0))
    else:
        scan, seed = _default_scan(args)
    xml = scan_to_xml(scan)        # before simulating: a scan that cannot be written fails early
    check_simulation_memory(scan.geometry, len(scan.test_angles), args.scene or "simulate")
    noise = (NoiseModel(I0=scan.noise["I0"], electronic_std=scan.noise["electronic_std"],
                        clip_negative=scan.noise["clip_negative"]) if scan.noise else None)
    t0 = time.perf_counter()
    case = simulate_case(scan.object["phantom"], scan.geometry, scan.test_angles, noise,
                         seed=seed, noise_seed=scan.noise["seed"] if scan.noise else None)
    case.info["scene"] = scan.info()          # echoed into metrics.json by reconstruct
    case.info["scene_xml"] = SCENE_XML
    with outputs.staged(args.out, outputs.SIMULATE) as tmp:   # an earlier one: replaced whole
        save_case(case, tmp, exr=args.exr)
        (tmp / SCENE_XML).write_text(xml)
    out = Path(args.out)
    geometry = scan.geometry
    print(f"wrote {out} ({geometry.n_views} train / {len(scan.test_angles)} test views, "
          f"{'x'.join(map(str, geometry.nVoxel))} volume, phantom {scan.object['phantom']}, "
          f"noise {'off' if noise is None else noise.to_dict()}, seed {seed}; scan as "
          f"{out / SCENE_XML}) in {time.perf_counter() - t0:.1f} s")
    return 0


def _check_option_values(method: str, options: dict, raw: dict) -> None:
    """An option given as text where the method's default is a number or a boolean is an
    error naming it (rather than a failure deep inside the method)."""
    import inspect

    from mi_grg.methods import get_method
    params = inspect.signature(get_method(method)).parameters
    for key, value in options.items():
        default = params[key].default if key in params else None
        if not isinstance(value, str) or default is None or isinstance(default, str):
            continue
        kind = "true or false" if isinstance(default, bool) else "a number"
        raise ValueError(f"--option {key}={raw[key]}: expected {kind} (default {default!r})")


def _run_method(args, out_dir, formats, options, raw) -> tuple:
    """reconstruct() into ``out_dir``, a temporary that becomes --out; a type error with
    options given as text names those options."""
    from mi_grg.methods import reconstruct
    try:
        return reconstruct(args.data, args.method, out_dir, formats=formats,
                           staged_for=args.out, **options)
    except (TypeError, ValueError) as e:
        texts = {k: raw[k] for k, v in options.items() if isinstance(v, str) and k in raw}
        named = {k: v for k, v in texts.items() if repr(v) in str(e)}
        if not texts or any(k in str(e) for k in texts) or not (
                named or isinstance(e, TypeError)):
            raise                  # an error about something else than a text option
        texts = [f"{k}={v}" for k, v in (named or texts).items()]
        raise ValueError(f"--option {', '.join(texts)}: passed as text, which the method "
                         f"could not use ({type(e).__name__}: {e}); expected a number, "
                         "true/false or JSON") from e


def _staged_run(args, formats, options) -> dict:
    """The run, written into a temporary beside --out that replaces --out only once it is
    complete (``mi_grg.data.outputs.staged``); with --resume it continues the run that
    stopped (its temporary's checkpoint), else --out's own checkpoint."""
    from mi_grg.data import outputs
    with outputs.staged_reconstruct(args.out, [args.data, args.config],
                                    args.resume) as (tmp, checkpoint):
        if checkpoint is not None:
            options["resume"] = checkpoint
        return _run_method(args, tmp, formats, options, _raw_options(args.option))[1]


def cmd_reconstruct(args) -> int:
    from mi_grg.data.export import parse_formats
    from mi_grg.methods import get_method
    formats = parse_formats(args.format)   # before any work
    options = _parse_options(args.option)
    get_method(args.method)
    _check_option_values(args.method, options, _raw_options(args.option))
    if args.config:
        options["config"] = args.config
    metrics = _staged_run(args, formats, options)
    summary = f"{args.method}: {metrics['seconds']:.1f} s"
    if "psnr_3d" in metrics:
        summary += f", PSNR {metrics['psnr_3d']:.2f} dB, SSIM {metrics['ssim_3d']:.3f}"
    print(summary + f"  -> {args.out}")
    return 0


def cmd_render(args) -> int:
    """Path-traced cross-check of a scene file or of a finished gr / r2 run; with
    --preview a 3-D view of a run's volume (mi_grg.evaluation.render_command)."""
    from mi_grg.evaluation.render_command import render_command
    return render_command(args)


def cmd_demo(args) -> int:
    """Simulate a noisy 25-view Shepp-Logan scan and reconstruct it with each method
    (GR-Gaussian takes 4-9 minutes on a 2-core CPU, 3000 iterations; the classical
    methods seconds)."""
    from mi_grg.methods import reconstruct
    out = Path(args.out)
    data = out / "shepp_64"
    # None = the flag's default (TIGRE's noise: I0 1e4, electronic std 10; seed 0)
    sim = argparse.Namespace(scene=None, phantom="shepp", n=args.n, det=args.det, views=25,
                             test_views=25, mode="cone", no_noise=None, I0=None,
                             electronic_std=None, seed=None, out=str(data), exr=False)
    cmd_simulate(sim)
    rows = []
    for method in args.methods.split(","):
        print(f"reconstructing with {method} ...", flush=True)
        _, m = reconstruct(data, method, out / method)
        rows.append(f"  {method:10s} {m['seconds']:7.1f} s   PSNR {m['psnr_3d']:6.2f} dB   "
                    f"SSIM {m['ssim_3d']:.3f}   -> {out / method}/slices.png")
    print("\n".join(["", f"{args.n}^3 Shepp-Logan, 25 noisy views (3-D PSNR/SSIM vs ground "
                      "truth):"] + rows))
    from mi_grg.evaluation.preview import write_preview
    methods = args.methods.split(",")
    shown = "gr" if "gr" in methods else methods[-1]
    p = write_preview(out / shown)
    print(f"3-D preview of {shown} ({p['seconds']:.0f} s): {p['png']}, {p['gif']}")
    return 0


def add_experiment_parser(subparsers) -> None:
    """Add the ``experiment`` and ``report`` sub-commands to an argparse subparsers."""
    from mi_grg.lab import runner
    from mi_grg.lab.suite import EXPERIMENTS
    e = subparsers.add_parser("experiment", help="run a scripted experiment of a suite",
                              description=runner.__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    e.add_argument("name", choices=(*EXPERIMENTS, "all"))
    e.add_argument("--suite", required=True, help="suite JSON (experiments/suite_cpu.json)")
    e.add_argument("--out", required=True, help="results directory")
    e.add_argument("--jobs", type=int, help="parallel runs (default: cores; 1 on a GPU)")
    e.add_argument("--methods", help="comma-separated methods or rows to keep (e.g. fdk,sart "
                                     "or gr-paper)")
    e.add_argument("--cases", help="comma-separated case names to keep")
    e.add_argument("--dry-run", action="store_true", help="print the plan, run nothing")
    e.add_argument("--dask", metavar="ADDRESS", help="run on the Dask cluster of this "
                   "scheduler (tcp://host:8786); OUT must be shared with its workers")
    e.add_argument("--threads-per-run", type=int, help="Dr.Jit threads of each run (default: "
                   "cores // jobs here, 1 with --dask)")
    _add_max_memory(e)
    e.set_defaults(func=cmd_experiment)
    r = subparsers.add_parser("report", help="write docs/results.md from a results directory")
    r.add_argument("--out", required=True, help="results directory (as given to experiment)")
    r.add_argument("--report", default="docs/results.md", help="markdown file to write")
    r.add_argument("--record", help="folder that keeps every finished run's metrics.json "
                   "(OUT's are copied in); its runs that OUT lacks are counted too")
    r.set_defaults(func=cmd_report)


def cmd_experiment(args) -> int:
    from mi_grg.lab.runner import run_experiment
    res = run_experiment(args.name, args.suite, args.out, jobs=args.jobs,
                         methods=args.methods, cases=args.cases, dry_run=args.dry_run,
                         dask=args.dask, threads_per_run=args.threads_per_run)
    if args.dry_run:
        for r in res["runs"]:
            extra = f" -> {r['target']}" if "target" in r else ""
            if r.get("stale"):
                extra += f" (ran with other defaults: {', '.join(r['stale'])})"
            if r.get("trains_with"):
                extra += f" (shares the training of {r['trains_with']}: result steps only)"
            if "resumes" in r:
                extra += (" (resumes from its checkpoint)" if r["resumes"] else
                          " (its checkpoint is of other training options: starts afresh)")
            print(f"{r['status']:12s} {r['experiment']}/{r['case']}/{r['run']}  "
                  f"[{r['method']} {json.dumps(r['options'])}]{extra}")
        print(f"{res['planned']} runs: {res.get('todo', 0)} to run, "
              f"{res.get('done before', 0)} done, {res.get('linked', 0) + res.get('duplicate', 0)}"
              f" shared; data to simulate: {', '.join(res['to_simulate']) or 'none'}")
        return 0
    print(f"{res['planned']} runs: {res['ran']} ran, {res['failed']} failed, "
          f"{res['done before']} done before, {res['linked']} linked -> {args.out}")
    for r in res["runs"]:
        if r["status"] == "failed":
            print(f"  FAILED {r['experiment']}/{r['case']}/{r['run']}: {r.get('error')}")
    return 1 if res["failed"] else 0


def cmd_report(args) -> int:
    from mi_grg.lab.report import write_report
    path = write_report(args.out, args.report, args.record)
    print(f"wrote {path}")
    return 0


def cmd_import(args) -> int:
    from mi_grg.data.raw_import import import_scan
    opts = {k: getattr(args, k) for k in (
        "flats", "darks", "free_ray", "cor", "bin", "train_views", "test_views", "seed",
        "reference", "nVoxel", "sVoxel", "scene", "angles", "angle_sign", "unit", "check",
        "overwrite", "max_memory", "geometry", "pixel_size")}
    rec = import_scan(args.source, args.out, **opts)
    cor = rec.get("cor", {})
    print(f"wrote {args.out}: {len(rec.get('views', {}).get('train', [])) or 'all'} train "
          f"views, offDetector[1] = {rec['geometry']['offDetector'][1]:.4g} "
          f"({cor.get('method', 'from the source')}"
          + (f", {cor['pixels']:.2f} +- {cor['uncertainty_pixels']:.2f} px" if
             "uncertainty_pixels" in cor else "") + f"); choices in {args.out}/import.json")
    return 0


def add_import_parser(sub) -> None:
    """The ``import`` sub-command (real scanner data)."""
    i = sub.add_parser("import", help="real scanner data (TIFF + FIPS text / scene XML, "
                       "NAF pickle) -> data set; see docs/real_data.md")
    i.add_argument("source", help="FIPS text file, Nikon .xtekct file, TIFF folder/glob "
                   "(with --scene or --geometry) or NAF .pickle")
    i.add_argument("--out", required=True)
    i.add_argument("--flats", help="glob of flat-field TIFFs (averaged)")
    i.add_argument("--darks", help="glob of dark TIFFs (averaged)")
    i.add_argument("--free-ray", default="auto", help="I0 columns: auto, none or A:B,C:D")
    i.add_argument("--cor", help="centre of rotation: auto or offDetector[1] in pixels")
    i.add_argument("--bin", type=int, default=1, help="sum B x B detector pixels")
    i.add_argument("--train-views", type=int, help="evenly spaced (default all)")
    i.add_argument("--test-views", type=int, default=0, help="drawn from the rest")
    i.add_argument("--seed", type=int, default=0, help="test-view draw")
    i.add_argument("--reference", choices=("fdk-all", "none"),
                   help="fdk-all: vol_gt.npy = FDK of all views (pseudo ground truth)")
    i.add_argument("--nVoxel", type=int, help="voxels across (default min(columns, 256))")
    i.add_argument("--sVoxel", type=float, help="cube edge (default: largest cylinder "
                   "every view sees)")
    i.add_argument("--scene", help="scene XML (ct_scanner) for a plain TIFF stack")
    i.add_argument("--angles", help="with --scene: angles file, degrees, one per line")
    i.add_argument("--geometry", help="per-view geometry for a TIFF stack: ASTRA vector "
                   "file (12 columns, one row per view) or RTK geometry .xml")
    i.add_argument("--pixel-size", type=float, help="with an RTK --geometry: detector "
                   "pixel pitch (length)")
    i.add_argument("--angle-sign", type=int, default=1, choices=(1, -1))
    i.add_argument("--unit", help="length unit name recorded (default mm; scene unit)")
    i.add_argument("--check", action="store_true", help="write OUT/check.png")
    i.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    i.add_argument("--max-memory", type=float, metavar="GIB", help="refuse an import whose "
                   "projections and volume need more (default: half of this machine's memory)")
    i.set_defaults(func=cmd_import)


class _Parser(argparse.ArgumentParser):
    """Usage errors in one line (the sub-parsers inherit this class)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _add_max_memory(parser) -> None:
    parser.add_argument("--max-memory", type=float, metavar="GIB", help="refuse work whose "
                        "volumes, projections, Gaussians and plans need more (default: the "
                        "memory this machine has available)")


def build_parser() -> argparse.ArgumentParser:
    from mi_grg.data.phantoms import PHANTOMS
    p = _Parser(prog="mi-grg", description=__doc__)
    p.add_argument("--variant", default=None, choices=("llvm_ad_mono", "cuda_ad_mono"),
                   help="Dr.Jit/Mitsuba variant (default: llvm_ad_mono, or $MI_GRG_VARIANT)")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="simulate a data set (R2-Gaussian layout)")
    # Defaults are None so that cmd_simulate can tell a flag given from one left out:
    # with --scene, the flags that the scene states are errors (see _SCENE_FIELDS).
    s.add_argument("--scene", help="scene XML describing scanner, phantom and noise; then "
                   "only --views/--test-views may override it")
    s.add_argument("--phantom", choices=PHANTOMS, help="default shepp")
    s.add_argument("--n", type=int, help="voxels per axis (default 64)")
    s.add_argument("--det", type=int, help="detector pixels per axis (default 96)")
    s.add_argument("--views", type=int, help="training views (default 25)")
    s.add_argument("--test-views", type=int, help="noise-free test views (default 25)")
    s.add_argument("--mode", choices=("cone", "parallel"), help="beam (default cone)")
    s.add_argument("--no-noise", action="store_true", default=None,
                   help="noise-free training views")
    s.add_argument("--I0", type=float, help="photons per pixel, Poisson (default 1e4)")
    s.add_argument("--electronic-std", type=float,
                   help="Gaussian electronic noise std, photon counts (default 10)")
    s.add_argument("--seed", type=int, help="phantom (needles, shells) and noise seed "
                   "(default 0)")
    s.add_argument("--exr", action="store_true", help="also write projections as OpenEXR")
    s.add_argument("--out", required=True)
    _add_max_memory(s)
    s.set_defaults(func=cmd_simulate)

    r = sub.add_parser("reconstruct", help="reconstruct a data set")
    r.add_argument("data", help="data-set directory (meta_data.json)")
    r.add_argument("--method", required=True)
    r.add_argument("--out", required=True)
    r.add_argument("--config", help="method config (scene XML), for methods that take one")
    r.add_argument("--option", action="append", metavar="KEY=VALUE",
                   help="method option, repeatable (e.g. --option n_iter=20)")
    r.add_argument("--resume", action="store_true",
                   help="r2 / gr: continue the run that stopped (Ctrl-C, a crash) or "
                   "OUT/checkpoint.npz (same options required)")
    r.add_argument("--format", action="append", metavar="NAMES",
                   help="volume files: npy, tiff (ImageJ), nifti (.nii.gz); comma list or "
                   "repeated (default npy,tiff)")
    _add_max_memory(r)
    r.set_defaults(func=cmd_reconstruct)

    q = sub.add_parser("render", help="path-traced cross-check (Mitsuba volpath vs the exact "
                       "transmittance) of a scene or of a finished gr / r2 run")
    q.add_argument("scene", nargs="?", help="scene XML: ct_scanner with a ct_phantom, "
                   "gaussian_medium or heterogeneous (gridvolume) medium, volpath, constant "
                   "emitter (scenes/*_volpath.xml)")
    q.add_argument("--run", metavar="OUT_DIR", help="instead of a scene: a finished gr / r2 "
                   "run (its gaussians.npz and metrics.json)")
    q.add_argument("--views", type=int, help="--run: test views to render (default 2)")
    q.add_argument("--det", type=int, help="--run: detector rows (default 32; columns in "
                   "proportion, physical size kept)")
    q.add_argument("--data", help="--run: the run's data set, for its test angles (default: "
                   "those metrics.json records)")
    q.add_argument("--spp", type=int, help="samples per pixel (default 256; --preview 4)")
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--confidence", type=float, default=0.999,
                   help="per-view confidence of pass/fail (default 0.999)")
    q.add_argument("--preview", action="store_true", help="with --run: write preview.png "
                   "and preview.gif, its volume rendered in 3-D (emission-absorption)")
    q.add_argument("--out", help="output directory (--preview: default the run's)")
    _add_max_memory(q)
    q.set_defaults(func=cmd_render)

    add_import_parser(sub)     # `import SOURCE --out CASE` (docs/real_data.md)

    add_experiment_parser(sub)  # `experiment NAME --suite FILE --out DIR` and `report`

    d = sub.add_parser("demo", help="built-in example: simulate Shepp-Logan, reconstruct")
    d.add_argument("--out", default="out/demo")
    d.add_argument("--n", type=int, default=64)
    d.add_argument("--det", type=int, default=96)
    d.add_argument("--methods", default="fdk,sart,asd-pocs,pdhg,gr")
    d.set_defaults(func=cmd_demo)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    import mi_grg
    from mi_grg.core import memory
    kept = os.environ.get(memory.ENV_MAX_MEMORY)
    try:
        _set_up(args, mi_grg, memory)
        return args.func(args)
    except SystemExit as e:
        if not isinstance(e.code, str):
            raise
        message = e.code
    except (ValueError, OSError, EOFError, MemoryError, RecursionError,
            zipfile.BadZipFile) as e:
        message = describe_error(e)
    except KeyboardInterrupt:   # Ctrl-C: what was kept is said above; no traceback
        print(f"mi-grg {args.command}: interrupted", file=sys.stderr)
        return 130
    finally:                    # an in-process caller's next command starts afresh
        os.environ.pop(memory.ENV_MAX_MEMORY, None)
        if kept is not None:
            os.environ[memory.ENV_MAX_MEMORY] = kept
    print(f"mi-grg {args.command}: error: {one_line(message)}", file=sys.stderr)
    return 2


def _set_up(args, mi_grg, memory) -> None:
    """--variant and --max-memory, before the command (their errors name the flag)."""
    if args.variant:
        try:
            mi_grg.set_variant(args.variant)
        except ValueError as e:
            raise ValueError(f"--variant {args.variant}: {e}") from None
    if args.command != "import" and getattr(args, "max_memory", None) is not None:
        memory.set_max_memory(args.max_memory)   # import checks its own sizes with it


if __name__ == "__main__":
    sys.exit(main())
