"""``mi-grg``: simulate, reconstruct, render (path-traced cross-check) and demo."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def _parse_options(items) -> dict:
    """``key=value`` pairs; values parsed as JSON where possible (numbers, true/false)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise SystemExit(f"--option expects key=value, got {item!r}")
        key, value = item.split("=", 1)
        try:
            out[key.replace("-", "_")] = json.loads(value)
        except json.JSONDecodeError:
            out[key.replace("-", "_")] = value
    return out


def cmd_simulate(args) -> int:
    import numpy as np
    from .dataset import save_case
    from .noise import NoiseModel
    from .simulate import default_geometry, default_test_angles, simulate_case

    if args.scene:
        from .scene import load_scan
        overrides = {k: v for k, v in (("views", args.views), ("test_views", args.test_views))
                     if v is not None}
        scan = load_scan(args.scene, overrides or None)
        geometry, test_angles = scan.geometry, scan.test_angles
        if args.n is not None or args.det is not None or args.mode is not None:
            raise SystemExit("--n/--det/--mode describe the scanner; with --scene edit the XML "
                             "(or leave out --scene)")
        phantom = args.phantom or scan.object.get("phantom")
        if phantom is None:
            raise SystemExit(f"{args.scene} names no phantom; pass --phantom")
        noise = NoiseModel(I0=scan.noise["I0"], electronic_std=scan.noise["electronic_std"]) \
            if scan.noise else None
        if args.no_noise:
            noise = None
        seed = scan.object.get("seed", args.seed)
        scene_info = scan.info()
    else:
        geometry = default_geometry(n=args.n or 64, det=args.det or 96,
                                    views=args.views or 25, mode=args.mode or "cone")
        test_views = 25 if args.test_views is None else args.test_views
        test_angles = default_test_angles(test_views) if test_views else np.zeros(0)
        phantom = args.phantom or "shepp"
        noise = None if args.no_noise else NoiseModel(I0=args.I0, electronic_std=args.electronic_std)
        seed, scene_info = args.seed, None
    t0 = time.perf_counter()
    case = simulate_case(phantom, geometry, test_angles, noise, seed=seed)
    if scene_info is not None:
        case.info["scene"] = scene_info
    out = save_case(case, args.out, exr=args.exr)
    print(f"wrote {out} ({geometry.n_views} train / {len(test_angles)} test views, "
          f"{'x'.join(map(str, geometry.nVoxel))} volume, noise "
          f"{'off' if noise is None else noise.to_dict()}) in {time.perf_counter() - t0:.1f} s")
    return 0


def cmd_reconstruct(args) -> int:
    from .methods import reconstruct
    options = _parse_options(args.option)
    if args.config:
        options["config"] = args.config
    vol, metrics = reconstruct(args.data, args.method, args.out, **options)
    summary = f"{args.method}: {metrics['seconds']:.1f} s"
    if "psnr_3d" in metrics:
        summary += f", PSNR {metrics['psnr_3d']:.2f} dB, SSIM {metrics['ssim_3d']:.3f}"
    print(summary + f"  -> {args.out}")
    return 0


def cmd_render(args) -> int:
    from .crosscheck import render_crosscheck
    result = render_crosscheck(args.scene, spp=args.spp, out_dir=args.out, seed=args.seed)
    print(json.dumps(result, indent=2, default=float))
    return 0


def cmd_demo(args) -> int:
    """Simulate a noisy 25-view Shepp-Logan scan and reconstruct it with each method
    (GR-Gaussian takes a few minutes on a 2-core CPU; the classical methods seconds)."""
    from .methods import reconstruct
    out = Path(args.out)
    data = out / "shepp_64"
    sim = argparse.Namespace(scene=None, phantom="shepp", n=args.n, det=args.det, views=25,
                             test_views=25, mode="cone", no_noise=False, I0=1e4,
                             electronic_std=10.0, seed=0, out=str(data), exr=False)
    cmd_simulate(sim)
    rows = []
    for method in args.methods.split(","):
        print(f"reconstructing with {method} ...", flush=True)
        _, m = reconstruct(data, method, out / method)
        rows.append(f"  {method:10s} {m['seconds']:7.1f} s   PSNR {m['psnr_3d']:6.2f} dB   "
                    f"SSIM {m['ssim_3d']:.3f}   -> {out / method}/slices.png")
    print("\n".join(["", f"{args.n}^3 Shepp-Logan, 25 noisy views (3-D PSNR/SSIM vs ground "
                      "truth):"] + rows))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mi-grg", description=__doc__)
    p.add_argument("--variant", default=None, choices=("llvm_ad_mono", "cuda_ad_mono"),
                   help="Dr.Jit/Mitsuba variant (default: llvm_ad_mono, or $MI_GRG_VARIANT)")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="simulate a data set (R2-Gaussian layout)")
    s.add_argument("--scene", help="scene XML describing scanner, phantom and noise")
    s.add_argument("--phantom", help="shepp | needles | shells")
    s.add_argument("--n", type=int, help="voxels per axis (default 64)")
    s.add_argument("--det", type=int, help="detector pixels per axis (default 96)")
    s.add_argument("--views", type=int, help="training views (default 25)")
    s.add_argument("--test-views", type=int, help="noise-free test views (default 25)")
    s.add_argument("--mode", choices=("cone", "parallel"), help="beam (default cone)")
    s.add_argument("--no-noise", action="store_true", help="noise-free training views")
    s.add_argument("--I0", type=float, default=1e4, help="photons per pixel (Poisson)")
    s.add_argument("--electronic-std", type=float, default=10.0, help="Gaussian noise std (counts)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--exr", action="store_true", help="also write projections as OpenEXR")
    s.add_argument("--out", required=True)
    s.set_defaults(func=cmd_simulate)

    r = sub.add_parser("reconstruct", help="reconstruct a data set")
    r.add_argument("data", help="data-set directory (meta_data.json)")
    r.add_argument("--method", required=True)
    r.add_argument("--out", required=True)
    r.add_argument("--config", help="method config (scene XML), for methods that take one")
    r.add_argument("--option", action="append", metavar="KEY=VALUE",
                   help="method option, repeatable (e.g. --option n_iter=20)")
    r.set_defaults(func=cmd_reconstruct)

    q = sub.add_parser("render", help="path-traced cross-check of a scene (volpath vs projector)")
    q.add_argument("scene")
    q.add_argument("--spp", type=int, default=256)
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--out", required=True)
    q.set_defaults(func=cmd_render)

    from .experiments import add_experiment_parser
    add_experiment_parser(sub)  # `experiment NAME --suite FILE --out DIR` and `report`

    d = sub.add_parser("demo", help="built-in example: simulate Shepp-Logan, reconstruct")
    d.add_argument("--out", default="out/demo")
    d.add_argument("--n", type=int, default=64)
    d.add_argument("--det", type=int, default=96)
    d.add_argument("--methods", default="fdk,sart,asd-pocs,gr")
    d.set_defaults(func=cmd_demo)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    import mi_grg
    if args.variant:
        mi_grg.set_variant(args.variant)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
