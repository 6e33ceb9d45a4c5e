"""The record: every finished run's metrics.json kept beside the report, so that a report
still counts the runs of a results folder that is gone.

    mi-grg report --out results/cpu --report docs/results.md --record docs/cpu/runs

``RECORD/<experiment>/runs.json`` and ``RECORD/<experiment>/<case>/<run>/metrics.json``, laid
out as the runner lays out OUT, without the volumes: each metrics.json is the run's own
with ``volume_files`` left out and ``record_of`` (the run folder it was copied from) added,
so it reads back without a volume (``mi_grg.lab.finished.run_problem``). A report with
``--record`` first copies every finished run of OUT into the record (replacing the earlier
copy of the same run), then counts the record's other runs beside OUT's: their numbers as
they were recorded; their volumes were not kept, so no new figure shows them, and the
report keeps its earlier figures of their cases. A run of OUT that did not
finish never removes a recorded one. The record alone is a results folder too:
``mi-grg report --out RECORD`` reports it.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

#: The key a recorded metrics.json gains: where it was copied from.
RECORD_OF = "record_of"


def _write_json(path: Path, obj) -> None:
    """``obj`` as JSON at ``path``, swapped in whole (never seen half-written); a file that
    already holds it is left untouched (a report rewrites no unchanged record)."""
    text = json.dumps(obj, indent=1, default=str) + "\n"
    if path.is_file() and path.read_text() == text:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def check_record(record: Path, out: Path, report: Path) -> None:
    """DatasetError (one line) unless ``record`` may be written: apart from OUT and from
    the report (and its image folder), and new, empty or a record (only experiment
    folders, each with its runs.json)."""
    from mi_grg.data.dataset import DatasetError
    from mi_grg.data.outputs import check_apart, check_writable
    from mi_grg.lab.suite import EXPERIMENTS
    check_apart(record, [out], "--record")
    for target in (report, report.parent / "img" / report.stem):
        check_apart(target, [record], "--report")
    check_writable(record, "--record")
    if record.is_dir():
        foreign = [p.name for p in record.iterdir()
                   if not (p.is_dir() and p.name in EXPERIMENTS and (p / "runs.json").is_file())]
        if foreign:
            raise DatasetError(f"--record {record}: holds {foreign[0]}, which no record "
                               "wrote (a record holds experiment folders with their "
                               "runs.json); give a new or empty folder")


def keep(out: Path, record: Path, loaded: dict) -> None:
    """Copy the finished runs of ``loaded`` ({experiment: rows of OUT, as
    ``report_tables.load_experiment`` reads them}) into ``record``, and merge their rows and
    the commands that made them into each experiment's runs.json there."""
    from mi_grg.lab.finished import METRICS, ROW_TYPES, read_runs
    for exp, rows in loaded.items():
        done = [r for r in rows if r.get("metrics")]
        if not done:
            continue
        for r in done:
            m = {k: v for k, v in r["metrics"].items() if k != "volume_files"}
            m[RECORD_OF] = str(Path(r["dir"]))
            _write_json(record / exp / r["case"] / r["run"] / METRICS, m)
        index = read_runs(record / exp / "runs.json") or {"runs": [], "commands": []}
        merged = {(x["case"], x["run"]): x for x in index["runs"]}
        merged.update({(r["case"], r["run"]): {k: r[k] for k in ROW_TYPES} for r in done})
        theirs = (read_runs(out / exp / "runs.json") or {"commands": []})["commands"]
        commands = index["commands"] + [c for c in theirs if c not in index["commands"]]
        _write_json(record / exp / "runs.json",
                    {"commands": commands, "runs": list(merged.values())})


def merge(loaded: dict, recorded: dict) -> dict:
    """OUT's rows, and after them the record's finished runs that OUT has not finished
    (each marked ``recorded``); OUT's unfinished rows of those runs are dropped."""
    merged = {}
    for exp in sorted({*loaded, *recorded}):
        mine = loaded.get(exp, [])
        have = {(r["case"], r["run"]) for r in mine if r.get("metrics")}
        extra = [{**r, "recorded": True} for r in recorded.get(exp, [])
                 if r.get("metrics") and (r["case"], r["run"]) not in have]
        taken = {(r["case"], r["run"]) for r in extra}
        merged[exp] = [r for r in mine if (r["case"], r["run"]) not in taken] + extra
    return merged
