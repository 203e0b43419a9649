"""docs/quickstart.md, run as written: a folder of 128x128 images with OpenGL camera poses
and depth PNGs becomes a session on the server a bare `worldpack serve` starts (the served
model), the way out observed, the way back generated and scored against the held-back
images. The page's commands are read from the page itself, so they cannot drift."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

from test_python_client import start

ROOT = Path(__file__).resolve().parent.parent
BIN = os.environ.get("WORLDPACK_BIN", str(ROOT / "target" / "release" / "worldpack"))
PAGE = ROOT / "docs" / "quickstart.md"


def page_commands() -> list[str]:
    """The commands of the page's `sh` blocks, in order."""
    blocks = re.findall(r"```sh\n(.*?)```", PAGE.read_text(), re.S)
    return [line.strip() for block in blocks for line in block.splitlines() if line.strip()]


def run(command: str, cwd: Path, url: str) -> str:
    """One of the page's commands, in `cwd`, with the repository's binary, venv and scripts
    and the test's server in place of the default address."""
    args = command.split()
    if args[0] == "target/release/worldpack":
        args[0] = BIN
    elif args[0] == ".venv/bin/python":
        args = [sys.executable, str(ROOT / args[1]), *args[2:]]
        if args[1].endswith("own_frames.py"):
            args += ["--url", url]
    out = subprocess.run(args, cwd=cwd, capture_output=True, text=True)
    assert out.returncode == 0, f"{command}\n{out.stdout}\n{out.stderr}"
    return out.stdout


def test_the_quickstart_runs_as_written_and_beats_holding_the_last_frame(tmp_path):
    commands = page_commands()
    assert commands[2] == "./scripts/serve.sh &", commands  # the page serves the served model...
    proc, url = start(tmp_path, bare=True)  # ...which is what a bare `worldpack serve` serves
    try:
        run(commands[0], tmp_path, url)
        made = run(commands[1], tmp_path, url)
        assert "wrote 187 frames" in made and "turns back after frame 105" in made, made
        printed = run(commands[3], tmp_path, url)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    cameras = json.loads((tmp_path / "my-frames" / "cameras.json").read_text())
    assert cameras["convention"] == "opengl" and cameras["intrinsics"]["width"] == 128
    assert "observed 106 frames; generating 81" in printed, printed
    model, held = map(float, re.search(r"PSNR ([\d.]+) dB.*held still: ([\d.]+) dB", printed).groups())
    assert model > held + 3, printed  # the model's frames, not a copy of the last one
    assert (tmp_path / "made" / "strip.png").exists() and (tmp_path / "made" / "0186.png").exists()
    from PIL import Image
    assert Image.open(tmp_path / "made" / "0186.png").size == (128, 128), "frames come back at the folder's size"



def test_a_folder_with_an_unknown_convention_is_refused_naming_the_field(tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    (folder / "cameras.json").write_text(json.dumps({"intrinsics": {}, "convention": "blender", "frames": [{}]}))
    out = subprocess.run([sys.executable, str(ROOT / "clients/python/examples/own_frames.py"), str(folder)],
                         capture_output=True, text=True)
    assert out.returncode != 0 and "`convention`" in out.stderr, out.stderr
