"""The report's per-case slices (mi_grg.lab.compare): which runs are shown, the figure's
volumes and scales, and the markdown that embeds it."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mi_grg.lab.compare import comparison_section, pick_runs

N = 12
# run -> (3-D PSNR, the constant its volume holds)
RUNS = {"fdk": (20.0, 0.1), "sart": (25.0, 0.2), "asd-pocs": (27.0, 0.3),
        "pdhg": (26.0, 0.4), "sart-fixed": (30.0, 0.5), "r2": (28.0, 0.6), "gr": (29.0, 0.7)}


def _results(tmp_path, runs=RUNS, cases=("shepp",), gt=True):
    out = tmp_path / "res"
    entries = []
    for case in cases:
        if gt:
            (out / "data" / case).mkdir(parents=True)
            np.save(out / "data" / case / "vol_gt.npy", np.full((N, N, N), 1.0, np.float32))
        for run, (psnr, value) in runs.items():
            d = out / "table1" / case / run
            d.mkdir(parents=True)
            np.save(d / "vol_pred.npy", np.full((N, N, N), value, np.float32))
            (d / "metrics.json").write_text(json.dumps(
                {"method": run.replace("-fixed", ""), "psnr_3d": psnr, "ssim_3d": 0.5,
                 "seconds": 1.0}))
            entries.append({"case": case, "run": run, "category": "HO", "label": run,
                            "method": run.replace("-fixed", ""), "views": 25})
    (out / "table1" / "runs.json").write_text(json.dumps({"runs": entries}))
    return out


def _rows(out):
    from mi_grg.lab.report import load_runs
    return load_runs(out)["table1"]


def test_best_classical_is_the_best_held_out_stopped_run(tmp_path):
    out = _results(tmp_path)
    picks = pick_runs(_rows(out), "shepp")
    assert [(t, r["run"]) for t, r in picks] == [
        ("FDK", "fdk"), ("best classical: ASD-POCS", "asd-pocs"), ("r2", "r2"), ("gr", "gr")]


def test_pdhg_under_morozovs_rule_competes_for_best_classical(tmp_path):
    out = _results(tmp_path, {**RUNS, "pdhg-morozov": (27.5, 0.45)})
    picks = pick_runs(_rows(out), "shepp")
    assert picks[1][0] == "best classical: PDHG (Morozov)" and picks[1][1]["run"] == "pdhg-morozov"


def test_missing_runs_leave_their_column_out(tmp_path):
    runs = {k: v for k, v in RUNS.items() if k in ("pdhg", "gr")}
    out = _results(tmp_path, runs)
    (out / "table1" / "shepp" / "gr" / "vol_pred.npy").unlink()     # an unfinished run
    assert [t for t, _ in pick_runs(_rows(out), "shepp")] == ["best classical: PDHG"]


def test_figure_shows_each_volume_on_one_grey_scale(tmp_path, monkeypatch):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.axes
    shown = []
    real = matplotlib.axes.Axes.imshow

    def spy(self, img, *a, **k):
        shown.append((float(np.mean(img)), k.get("cmap"), k.get("vmin"), k.get("vmax")))
        return real(self, img, *a, **k)
    monkeypatch.setattr(matplotlib.axes.Axes, "imshow", spy)
    out = _results(tmp_path)
    md = comparison_section(out, _rows(out), tmp_path / "img", "img")
    assert "![shepp](img/compare_shepp.png)" in md
    assert (tmp_path / "img" / "compare_shepp.png").stat().st_size > 1000
    grey = [s for s in shown if s[1] == "gray"]
    err = [s for s in shown if s[1] == "magma"]
    # ground truth, FDK, ASD-POCS, r2, gr: their values, all on [0, max(gt)] = [0, 1]
    assert [round(m, 3) for m, *_ in grey] == [1.0, 0.1, 0.3, 0.6, 0.7]
    assert {(lo, hi) for _, _, lo, hi in grey} == {(0, 1.0)}
    assert [round(m, 3) for m, *_ in err] == [0.9, 0.7, 0.4, 0.3]
    assert {(lo, hi) for _, _, lo, hi in err} == {(0, 0.25)}


def test_no_ground_truth_no_figure(tmp_path):
    out = _results(tmp_path, gt=False)
    md = comparison_section(out, _rows(out), tmp_path / "img", "img")
    assert "No case has both a ground truth and a finished run." in md
    assert not list(tmp_path.rglob("*.png"))


def test_report_embeds_the_section(tmp_path):
    from mi_grg.lab.report import write_report
    out = _results(tmp_path, cases=("shepp", "bone"))
    md = write_report(out, tmp_path / "docs" / "results.md").read_text()
    section = md.split("## Slices per case", 1)[1].split("\n## ", 1)[0]
    for case in ("bone", "shepp"):
        assert f"![{case}](img/results/compare_{case}.png)" in section
        assert (tmp_path / "docs" / "img" / "results" / f"compare_{case}.png").is_file()


@pytest.fixture(autouse=True)
def _agg():
    import matplotlib
    matplotlib.use("Agg")
