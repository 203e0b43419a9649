"""scripts/rest_walk.py against real `worldpack serve` processes: draws of the
sampler's noise, rows with their own sampler steps, rows reused
from an earlier walk, and its errors."""

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
    # The draw furthest behind, and the median (of two draws, their mean), from the rounded walks.
    diffs = [t - s for t, s in zip(draws, across["way_back_db"]["served"][0])]
    worst = min(range(2), key=lambda i: diffs[i])
    assert paired["worst"]["unit"] == worst and abs(paired["worst"]["diff_db"] - diffs[worst]) <= 0.011, (paired, diffs)
    assert abs(paired["median_db"] - sum(diffs) / 2) <= 0.011, (paired, diffs)
    assert f"furthest behind {paired['worst']['diff_db']:+.2f} (draw {worst})" in many.stdout, many.stdout
    assert "2 draw(s) each, per draw" in many.stdout


def test_a_reused_row_pairs_as_if_it_were_walked_again(tmp_path):
    both = walk(tmp_path, "both", "--draws", "2", "--row", STUDENT, "--row", TEACHER_2)
    assert both.returncode == 0, both.stdout + both.stderr
    cached = f"{tmp_path / 'both.json'}:served"
    again = walk(tmp_path, "again", "--draws", "2", "--reuse", cached, "--row", TEACHER_2)
    assert again.returncode == 0, again.stdout + again.stderr
    first = json.loads((tmp_path / "both.json").read_text())
    second = json.loads((tmp_path / "again.json").read_text())
    assert second["steps_per_row"] == {"served": 10, "teacher_2": 2}
    # The same step seeds give the same frames, so the walked row repeats itself exactly.
    assert second["across_worlds"]["way_back_db"] == first["across_worlds"]["way_back_db"]
    was, now = first["across_worlds"]["against_served"]["teacher_2"], second["across_worlds"]["against_served"]["teacher_2"]
    # The reused way-back values are rounded to 0.01 dB (their mean moves by up to 0.005) and
    # both differences are rounded again (0.005 each): up to 0.015 apart.
    assert abs(was["diff_db"] - now["diff_db"]) <= 0.015 + 1e-9 and was["wins"] == now["wins"], (was, now)
    assert second["rows"]["served"]["steps"] == first["rows"]["served"]["steps"]
    refused = walk(tmp_path, "refused", "--draws", "3", "--reuse", cached, "--row", TEACHER_2)
    assert refused.returncode != 0 and "that walk had draws 2, this one 3" in refused.stderr, refused.stderr
    assert not (tmp_path / "refused.json").exists()


def test_bad_rows_and_draws_are_refused_by_name(tmp_path):
    for args, words in [(["--row", "x=folder:worldpack:0"], "--row 'x=folder:worldpack:0'"),
                        (["--row", "nofolder"], "--row 'nofolder'"),
                        (["--draws", "0", "--row", STUDENT], "--draws 0"),
                        (["--reuse", f"{tmp_path}/none.json:served"], "--reuse"),
                        (["--row", STUDENT, "--row", STUDENT], "each row needs its own name")]:
        out = walk(tmp_path, "bad", *args)
        assert out.returncode != 0 and words in out.stderr, out.stderr
        assert not (tmp_path / "bad.json").exists()
