"""scripts/rest_walk.py against real `worldpack serve` processes: draws of the
sampler's noise, rows with their own sampler steps, and its errors."""

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BIN = os.environ.get("WORLDPACK_BIN", str(ROOT / "target" / "release" / "worldpack"))
STUDENT = f"served={ROOT}/fixtures/variants/worldpack_geometry_fused_1step:worldpack"
TEACHER_2 = f"teacher_2={ROOT}/fixtures/variants/worldpack_geometry_fused:worldpack:2"


def walk(tmp_path, name, *args):
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "rest_walk.py"), "--bin", BIN, "--observe-outbound",
                          "--covisible", "--seed", "3", "--out", str(tmp_path / name), *args],
                         capture_output=True, text=True, timeout=900)
    return out


def test_draws_pair_rows_over_the_noise_and_draw_zero_is_the_single_walk(tmp_path):
    single = walk(tmp_path, "single", "--row", TEACHER_2)
    assert single.returncode == 0, single.stdout + single.stderr
    many = walk(tmp_path, "many", "--draws", "2", "--row", STUDENT, "--row", TEACHER_2)
    assert many.returncode == 0, many.stdout + many.stderr
    one = json.loads((tmp_path / "single.json").read_text())
    two = json.loads((tmp_path / "many.json").read_text())
    assert two["steps_per_row"] == {"served": 10, "teacher_2": 2}
    across = two["across_worlds"]
    assert across["unit"] == "draws" and across["draws"] == 2
    draws = across["way_back_db"]["teacher_2"][0]
    assert len(draws) == 2 and draws[0] != draws[1], draws  # other seeds, other frames
    assert draws[0] == one["mean_psnr_db_by_phase"]["teacher_2"]["back"]  # draw 0 is the single walk
    paired = across["against_served"]["teacher_2"]
    assert paired["units"] == 2 and paired["ci95"][0] <= paired["diff_db"] <= paired["ci95"][1]
    assert "2 draw(s) each, per draw" in many.stdout


def test_bad_rows_and_draws_are_refused_by_name(tmp_path):
    for args, words in [(["--row", "x=folder:worldpack:0"], "--row 'x=folder:worldpack:0'"),
                        (["--row", "nofolder"], "--row 'nofolder'"),
                        (["--draws", "0", "--row", STUDENT], "--draws 0")]:
        out = walk(tmp_path, "bad", *args)
        assert out.returncode != 0 and words in out.stderr, out.stderr
        assert not (tmp_path / "bad.json").exists()
