"""Every `mi-grg ...` line in the code blocks of README.md and docs/*.md runs as written.

The cheap lines (simulate, reconstruct with a classical method, render) run in order in a
temporary folder (with ``scenes/`` linked in, since the lines name it relative to the
repository root); the expensive ones (training, experiment suites, the report over their
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


def readme_lines() -> list:
    """(file, argv) of every `mi-grg` command line in a fenced code block, in order."""
    out = []
    for path in DOCS:
        blocks = re.findall(r"^```[^\n]*\n(.*?)^```", path.read_text(), re.M | re.S)
        for block in blocks:
            for line in block.replace("\\\n", " ").splitlines():
                if line.strip().startswith("mi-grg "):
                    argv = shlex.split(line, comments=True)[1:]
                    out.append((path.relative_to(ROOT).as_posix(), argv))
    return out


def parse_only_reason(argv):
    line = " ".join(argv)
    for (command, word), reason in PARSE_ONLY.items():
        if argv[0] == command and word in line:
            return reason
    return None


LINES = readme_lines()


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
    """simulate / reconstruct fdk / render lines run in order and exit 0."""
    from mi_grg.cli import main
    (tmp_path / "scenes").symlink_to(ROOT / "scenes")
    monkeypatch.chdir(tmp_path)
    ran = []
    for where, argv in LINES:
        if parse_only_reason(argv):
            continue
        try:
            rc = main(list(argv))
        except SystemExit as e:    # argparse and explicit refusals
            rc = e.code
        assert rc == 0, f"{where}: `mi-grg {' '.join(argv)}` exited {rc}"
        ran.append(argv[0])
    assert {"simulate", "reconstruct", "render"} <= set(ran), ran
