"""``mi-grg render``: its flags checked before anything is written, the cross-check (or,
with --preview, the 3-D view) built beside --out and swapped in whole, the result printed.
"""
from __future__ import annotations

from pathlib import Path


#: Bounds of render's options, checked before anything is written: past them a render
#: takes hours or more memory than a workstation has.
RENDER_BOUNDS = {"spp": 1 << 16, "views": 360, "det": 4096}


def _check_render_options(args) -> None:
    """render's flags, each checked alone (one-line errors naming the flag)."""
    for key, top in RENDER_BOUNDS.items():
        value = getattr(args, key)
        if value is not None and not 1 <= value <= top:
            raise ValueError(f"--{key} {value}: expected 1 to {top}")
    if not 0.5 < args.confidence < 1.0:
        raise ValueError(f"--confidence {args.confidence}: expected a value in (0.5, 1)")
    if (args.scene is None) == (args.run is None):
        raise ValueError("give a scene file (SCENE, e.g. scenes/shepp_cone_volpath.xml) or a "
                         "finished gr / r2 run (--run OUT_DIR), not both or neither")
    run_only = [f for f, v in (("--views", args.views), ("--det", args.det),
                               ("--data", args.data)) if v is not None]
    if args.scene is not None and run_only:
        raise ValueError(f"{', '.join(run_only)} only apply with --run (a scene file states "
                         "its own views and detector)")


def render_command(args) -> int:
    """Path-traced cross-check of a scene file or of a finished gr / r2 run; exit 1 when a
    view fails (crosscheck.json and crosscheck.png say where). With --preview: a
    Mitsuba-rendered 3-D view of a run's volume (mi_grg.evaluation.preview). The output is
    built beside --out and swapped in whole (``mi_grg.data.outputs``)."""
    if args.preview:
        from mi_grg.evaluation.preview import preview_command
        return preview_command(args)
    if args.out is None:
        raise ValueError("--out DIR is required (only --preview writes into the run itself)")
    _check_render_options(args)
    spp = 256 if args.spp is None else args.spp
    from mi_grg.data import outputs
    from mi_grg.evaluation import crosscheck as cc
    from mi_grg.evaluation.crosscheck_run import render_run
    outputs.check_out(args.out, outputs.RENDER, [args.scene, args.run, args.data])
    with outputs.staged(args.out, outputs.RENDER) as tmp:
        if args.scene is not None:
            res = cc.render_scene(args.scene, spp, tmp, seed=args.seed,
                                  confidence=args.confidence, shown=args.out)
        else:
            res = render_run(args.run, spp, tmp, views=args.views or 2,
                             det=args.det or 32, data=args.data, seed=args.seed,
                             confidence=args.confidence, shown=args.out)
    print(f"volpath ({res['spp']} spp) vs {res['reference']}, {res['confidence']:.1%} "
          "confidence per view:")
    for k, v in enumerate(res["views"]):
        print(f"  view {k} ({v['angle_deg']:6.1f} deg): RMS diff {v['rms_difference']:.4f} "
              f"(MC standard error {v['expected_rms_standard_error']:.4f}), max "
              f"{v['max_abs_difference']:.4f}, z {v['z']:+.2f}  "
              f"{'pass' if v['pass'] else 'FAIL'}")
    print(f"{'PASS' if res['pass'] else 'FAIL'}  -> {Path(args.out) / 'crosscheck.png'}, "
          "crosscheck.json")
    return 0 if res["pass"] else 1
