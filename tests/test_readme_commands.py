"""Every `mi-grg ...` line in the code blocks of README.md and docs/*.md runs as written.

The cheap lines (simulate, import, reconstruct with a classical method, render) of each page
run in order in a temporary folder of their own (with ``scenes/`` linked in, since the lines name it relative to the
repository root), together with the ``python docs/...`` lines that make their inputs; the
expensive ones (training, experiment suites, the report over their
results) are listed by name in ``PARSE_ONLY`` with the reason, and must at least parse:
the subcommand, its options, the method and the files they name exist."""
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

#: (subcommand, word that must appear in the line) -> why the line is only parsed here.
PARSE_ONLY = {
    ("reconstruct", "--method gr"): "gr training takes minutes (tests/test_train.py covers it)",
    ("experiment", ""): "experiment suites take tens of minutes to hours",
    ("report", ""): "needs the finished experiment runs of results/cpu",
    ("render", "--run"): "needs the gr run of the line above (tests/test_crosscheck.py runs "
                         "`render --run` on a run folder of its own)",
}


def readme_lines(program: str = "mi-grg") -> list:
    """(file, argv) of every command line of ``program`` in a fenced code block, in order
    (lines that start the line; indented ones belong to diagrams)."""
    out = []
    for path in DOCS:
        blocks = re.findall(r"^```[^\n]*\n(.*?)^```", path.read_text(), re.M | re.S)
        for block in blocks:
            for line in block.replace("\\\n", " ").splitlines():
                if line.startswith(program + " "):
                    argv = shlex.split(line, comments=True)[1:]
                    out.append((path.relative_to(ROOT).as_posix(), argv))
    return out


def parse_only_reason(argv):
    line = " ".join(argv)
    command_at = 2 if argv[0] == "--variant" else 0    # after the global option
    for (command, word), reason in PARSE_ONLY.items():
        if argv[command_at] == command and word in line:
            return reason
    return None


LINES = readme_lines()
#: ``python docs/SCRIPT ...`` lines: they make the inputs of the lines after them.
SCRIPT_LINES = [(f, a) for f, a in readme_lines("python") if a[0].startswith("docs/")]


def test_the_readme_has_command_lines():
    commands = {argv[0] for f, argv in LINES if f == "README.md"}
    assert {"simulate", "reconstruct", "render"} <= commands, LINES
    # every entry of PARSE_ONLY still names a line (the list cannot go stale)
    for (command, word) in PARSE_ONLY:
        assert any(a[0] == command and word in " ".join(a) for _, a in LINES), (command, word)


@pytest.mark.parametrize("where, argv", LINES, ids=[" ".join(a)[:60] for _, a in LINES])
def test_every_line_parses(where, argv):
    """The subcommand and its options exist; named methods and input files exist."""
    from mi_grg.cli import build_parser
    from mi_grg.methods import available_methods
    args = build_parser().parse_args(argv)
    if getattr(args, "method", None) is not None:
        assert args.method in available_methods(), (where, argv)
    for name in ("config", "suite"):
        value = getattr(args, name, None)
        if value:
            assert (ROOT / value).is_file(), f"{where}: {' '.join(argv)}: {value} missing"
    scene = getattr(args, "scene", None)
    if scene and scene.startswith("scenes/"):
        assert (ROOT / scene).is_file(), f"{where}: {scene} missing"


def test_cheap_lines_run_as_written(tmp_path, monkeypatch):
    """simulate / import / reconstruct fdk / render lines run in order and exit 0; each
    page in a folder of its own, as a reader following that page would."""
    import subprocess
    import sys
    from mi_grg.cli import main
    ran = []
    for page in dict.fromkeys(f for f, _ in LINES):
        folder = tmp_path / page.replace("/", "_")
        folder.mkdir()
        (folder / "scenes").symlink_to(ROOT / "scenes")
        monkeypatch.chdir(folder)
        for where, argv in SCRIPT_LINES:
            if where != page:
                continue
            r = subprocess.run([sys.executable, str(ROOT / argv[0]), *argv[1:]],
                               capture_output=True, text=True)
            assert r.returncode == 0, f"{where}: `python {' '.join(argv)}`: {r.stderr[-2000:]}"
        for where, argv in LINES:
            if where != page or parse_only_reason(argv):
                continue
            try:
                rc = main(list(argv))
            except SystemExit as e:    # argparse and explicit refusals
                rc = e.code
            assert rc == 0, f"{where}: `mi-grg {' '.join(argv)}` exited {rc}"
            ran.append(argv[0])
    assert {"simulate", "import", "reconstruct", "render"} <= set(ran), ran
