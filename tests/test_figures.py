"""The README's figures are its saved runs': `scripts/figures.py render --check` rebuilds
the table from docs/figures/*.json and fails when the README differs; every saved figure
names the command that made it."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FIGURES = ROOT / "docs" / "figures"


def render(*args):
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "figures.py"), "render", *args],
                          capture_output=True, text=True, cwd=ROOT, env={"PYTHONPATH": str(ROOT / "train")})


def test_the_readme_table_is_rendered_from_the_saved_runs():
    out = render("--check")
    assert out.returncode == 0, out.stderr


def test_every_saved_figure_names_its_command():
    saved = sorted(FIGURES.glob("*.json"))
    assert saved, "docs/figures holds no saved runs"
    for path in saved:
        command = json.loads(path.read_text()).get("command", "")
        assert command.startswith(("./scripts/", "target/release/worldpack", "taskset")), f"{path.name}: {command!r}"


def test_an_edited_figure_is_caught(tmp_path):
    readme = (ROOT / "README.md").read_text()
    table_end = readme.index("<!-- /figures -->")
    # One digit of the table changed, in a copy: the check must fail.
    i = next(j for j in range(table_end - 1, 0, -1) if readme[j].isdigit())
    copy = tmp_path / "README.md"
    copy.write_text(readme[:i] + str((int(readme[i]) + 1) % 10) + readme[i + 1:])
    assert render("--check", "--readme", str(copy)).returncode != 0
