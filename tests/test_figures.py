"""The pages' figures are their saved runs': `scripts/figures.py render --check` rebuilds
the README's table and every page's figure spans from docs/figures/*.json and fails when a
page differs; every saved figure names the command that made it."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

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


def test_a_span_is_rewritten_from_its_source_and_a_wrong_one_is_named():
    sys.path.insert(0, str(ROOT / "scripts"))
    sys.path.insert(0, str(ROOT / "train"))
    import figures

    served = json.loads((FIGURES / "voxel-test.json").read_text())["rows"]["served_covisible"]["psnr"]
    page = "at <!--fig voxel-test rows.served_covisible.psnr ci2-->99.99 [1.00, 2.00]<!--/fig--> dB"
    want = f"{served['mean']:.2f} [{served['lo']:.2f}, {served['hi']:.2f}]"
    assert figures.with_spans(page) == page.replace("99.99 [1.00, 2.00]", want)
    for wrong in ("<!--fig voxel-test rows.nobody.psnr 2-->1<!--/fig-->", "<!--fig nowhere rows 2-->1<!--/fig-->"):
        with pytest.raises(SystemExit):
            figures.with_spans(wrong)


def test_the_pages_quote_their_figures_as_spans():
    """The served models' headline figures on the user pages come from the saved runs."""
    quoted = {page.name: page.read_text().count("<!--fig ") for page in (ROOT / "docs").glob("*.md")}
    for page in ("api.md", "benchmarks.md", "model.md", "doom.md", "miniworld.md", "geometry.md"):
        assert quoted.get(page, 0) > 0, f"docs/{page} quotes no figure span"
