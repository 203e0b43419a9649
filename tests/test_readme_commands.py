"""The README's quick figures, by their own commands: every row of "What it does today"
whose command fits CI's time (the benchmarks; the evals are long and their saved runs
render the table, tests/test_figures.py) is run exactly as the README writes it, then again
with --json, and the row those outputs render has the README row's shape. No time is
asserted: the figures are the machine's."""

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "scripts"))
sys.path.insert(0, str(ROOT / "train"))
import figures  # noqa: E402


def rows():
    """(what, figure, command) of the README's table."""
    text = (ROOT / "README.md").read_text()
    table = text.split(figures.BEGIN, 1)[1].split(figures.END, 1)[0]
    out = []
    for line in table.strip().splitlines()[2:]:
        what, figure, command = (c.strip() for c in line.strip().strip("|").split(" | "))
        out.append((what, figure, command.strip("`")))
    return out


QUICK = [r for r in rows() if r[2].startswith(("target/release/worldpack bench", "taskset -c 0 target/release/worldpack bench"))]


def shape(text: str) -> str:
    return re.sub(r"\d[\d,]*(\.\d+)?", "#", text)


def test_the_table_has_quick_rows():
    assert {"walk", "select"} <= {c.split()[c.split().index("bench") + 1] for _, _, c in QUICK}, QUICK


@pytest.mark.parametrize("what,figure,command", QUICK, ids=[c.split("bench ")[1].split()[0] for _, _, c in QUICK])
def test_a_quick_row_is_its_commands_output(what, figure, command, tmp_path, monkeypatch):
    as_written = subprocess.run(shlex.split(command), capture_output=True, text=True, cwd=ROOT, timeout=900)
    assert as_written.returncode == 0, as_written.stderr[-2000:]
    assert any(ch.isdigit() for ch in as_written.stdout), as_written.stdout
    measured = subprocess.run(shlex.split(command) + ["--json"], capture_output=True, text=True, cwd=ROOT, timeout=900)
    assert measured.returncode == 0, measured.stderr[-2000:]
    name = "walk" if " walk" in command else "select-loop"
    saved = json.loads((figures.FIGURES / f"{name}.json").read_text())
    assert saved["command"] == command, "the README's command is the one its figure was saved with"
    # The row as the fresh output renders it, beside the saved runs of the other quick figure.
    for other in ("walk", "select-loop"):
        (tmp_path / f"{other}.json").write_text((figures.FIGURES / f"{other}.json").read_text())
    (tmp_path / f"{name}.json").write_text(json.dumps({"command": command, "report": json.loads(measured.stdout)}))
    monkeypatch.setattr(figures, "FIGURES", tmp_path)
    rendered = {r[0]: r[1] for r in figures.speed_rows()}
    assert shape(rendered[what]) == shape(figure), (rendered[what], figure)
