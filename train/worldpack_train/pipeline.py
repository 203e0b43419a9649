"""`worldpack train`: a dataset folder to a served model folder, every stage of
the served recipe in order, each resumable, with its lineage recorded.

The output folder is the model (`serve --model OUT` serves it as its card
measured it) and holds beside it:
  train.json    the settings (world defaults + flags), read back on every rerun
  lineage.json  per stage: status, settings, inputs and outputs with digests, minutes
  train.log     everything every sitting printed
  MODEL.md      the card (card.py)
  baseline/, teacher/  its own 4-frame baseline and the 10-step model the student
                was distilled from (what `--from OUT` fine-tunes)
  work/         checkpoints, latents, the held-out split, eval rows (not served)
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import time
import traceback

import numpy as np
import onnxruntime as ort
import torch

from . import budget, card
from . import settings as wsettings
from .core.config import ModelConfig
from .core.recipe import Recipe
from .io.manifest import set_warp_frames
from .stages.autoencoder import encode, train_autoencoder
from .stages.denoiser import train_cdit
from .stages.distill import distill
from .stages import fusion
from .stages.export import export
from .stages.recover import recover

# Files a trajectory view links to; plans are the view's own (`worldpack plan` writes them).
TRAJECTORY_FILES = ("meta.json", "rgb.npy", "poses.npy", "actions.npy", "phase.npy", "depth.npy", "pose5.npy")


class StageFailed(Exception):
    pass


def file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()[:16]


def folder_digest(folder: Path) -> str:
    """Every file's name and content under `folder`, in sorted order (links followed)."""
    h = hashlib.sha256()
    for p in sorted(q for q in folder.rglob("*") if q.is_file()):
        h.update(str(p.relative_to(folder)).encode())
        h.update(file_digest(p).encode())
    return h.hexdigest()[:16]


def suite_digest(data: Path) -> str:
    """The dataset's identity: its index and each trajectory's files the trainer reads."""
    h = hashlib.sha256(file_digest(data / "index.json").encode())
    for t in json.loads((data / "index.json").read_text())["trajectories"]:
        for name in TRAJECTORY_FILES:
            p = data / t["dir"] / name
            if p.exists():
                h.update(f"{t['dir']}/{name}:{file_digest(p)}".encode())
    return h.hexdigest()[:16]


class Tee:
    """Writes what the run prints to the terminal and to train.log."""

    def __init__(self, stream, log):
        self.stream, self.log = stream, log

    def write(self, s):
        self.stream.write(s)
        self.log.write(s)
        return len(s)

    def flush(self):
        self.stream.flush()
        self.log.flush()

    def isatty(self):
        return self.stream.isatty()


def runtime_env() -> dict:
    """The binary loads ONNX Runtime at run time: this venv's, unless ORT_DYLIB_PATH names one."""
    env = dict(os.environ)
    if "ORT_DYLIB_PATH" not in env:
        libs = sorted((Path(ort.__file__).parent / "capi").glob("libonnxruntime.so*"))
        if libs:
            env["ORT_DYLIB_PATH"] = str(libs[-1])
    return env


class Run:
    """The output folder, its settings and its lineage."""

    def __init__(self, out: Path, data: Path, binary: Path, repo: Path):
        self.out, self.data, self.binary, self.repo = out, data, binary, repo
        self.work = out / "work"
        self.settings = json.loads((out / "train.json").read_text())
        wsettings.check(self.settings)
        path = out / "lineage.json"
        self.lineage = json.loads(path.read_text()) if path.exists() else {"format": "worldpack-lineage/1", "stages": {}}

    def save(self) -> None:
        tmp = self.out / "lineage.json.tmp"
        tmp.write_text(json.dumps(self.lineage, indent=2))
        tmp.replace(self.out / "lineage.json")

    def stage(self, name: str) -> dict:
        return self.lineage["stages"].setdefault(name, {"status": "pending", "minutes": 0.0})

    def worldpack(self, *args: str) -> str:
        """Runs the product binary; its output goes to the log; a failure raises with its last lines."""
        cmd = [str(self.binary), *args]
        print("$ worldpack " + " ".join(args), flush=True)
        p = subprocess.run(cmd, capture_output=True, text=True, env=runtime_env())
        sys.stdout.write(p.stdout)
        sys.stdout.write(p.stderr)
        if p.returncode != 0:
            raise StageFailed(f"`worldpack {' '.join(args)}` exited {p.returncode}: {(p.stderr or p.stdout).strip()[-600:]}")
        return p.stdout

    def split_views(self) -> tuple[list, list]:
        """The training and held-out walks: the split's views once made, else what it will make."""
        views = self.work / "data" / "train" / "index.json", self.work / "data" / "heldout" / "index.json"
        if all(v.exists() for v in views):
            return tuple(json.loads(v.read_text())["trajectories"] for v in views)
        trajs = json.loads((self.data / "index.json").read_text())["trajectories"]
        folder = self.settings["heldout"]["folder"]
        if folder:
            return trajs, json.loads((Path(folder) / "index.json").read_text())["trajectories"]
        picked = budget.heldout_picks(len(trajs), self.settings["heldout"])
        return [t for i, t in enumerate(trajs) if i not in picked], [t for i, t in enumerate(trajs) if i in picked]

    def work_ahead(self) -> dict[str, float]:
        return budget.work_ahead(self.settings, self.lineage["stages"], *self.split_views())

    def training_pool(self) -> float:
        return budget.training_pool(self.settings, self.lineage["stages"], self.work_ahead())

    def training_minutes(self, name: str) -> float:
        return budget.training_minutes(self.settings, self.lineage["stages"], self.work_ahead(), name)


# --- the stages -------------------------------------------------------------------------------


def check_data(data: Path, binary: Path, settings: dict) -> dict:
    """Before anything is written: the dataset format, then what training needs beyond it."""
    p = subprocess.run([str(binary), "check", "--data", str(data)], capture_output=True, text=True)
    if p.returncode != 0:
        raise SystemExit((p.stderr or p.stdout).strip() + "\n(fix the dataset and run the same command again)")
    index = json.loads((data / "index.json").read_text())
    trajs = index["trajectories"]
    meta = json.loads((data / trajs[0]["dir"] / "meta.json").read_text())
    k = meta["intrinsics"]
    if (k["width"], k["height"]) != (64, 64):
        raise SystemExit(f"--data: {data}: frames are {k['width']}x{k['height']}; the models take 64x64 "
                         "(resize them and scale the intrinsics: `worldpack geometry` op `resize`)")
    if abs(k["fx"] - k["fy"]) > 1e-6 * k["fx"]:
        raise SystemExit(f"--data: {data}: field `intrinsics`: fx {k['fx']} and fy {k['fy']} differ; the CDiT's "
                         "landing rays assume square pixels")
    no_depth = [t["dir"] for t in trajs if not (data / t["dir"] / "depth.npy").exists()]
    if no_depth:
        raise SystemExit(f"--data: {data}/{no_depth[0]}/depth.npy: missing ({len(no_depth)} trajectories without depth); "
                         "the geometry model warps stored frames with their depth")
    held = settings["heldout"]
    if held["folder"] is None and len(trajs) < 2 + held["at_least"]:
        raise SystemExit(f"--data: {data}: {len(trajs)} trajectories; a held-out split needs at least "
                         f"{2 + held['at_least']} (or give --heldout DIR)")
    return {"trajectories": len(trajs), "frames": sum(t["frames"] for t in trajs), "kind": index.get("kind"),
            "intrinsics": k, "focal": k["fx"] / k["width"], "check": p.stdout.strip()}


def check_family(settings: dict, focal: float) -> list[str]:
    """The model fine-tuned from must take these frames; its focal is adapted (it only places landing rays)."""
    notes = []
    fam = settings["from"]
    if fam is None:
        return notes
    for role, folder in fam.items():
        m = json.loads((Path(folder) / "manifest.json").read_text())
        w, h = m["image"]["width"], m["image"]["height"]
        if (w, h) != (64, 64):
            raise SystemExit(f"--from: {folder} takes {w}x{h} frames, the data 64x64")
        theirs = m["config"]["cdit"].get("focal") or 0.0
        if theirs and abs(theirs - focal) > 1e-3 and role == "teacher":
            notes.append(f"the data's focal (fx / width) is {focal:.4f}, {Path(folder).name}'s {theirs:.4f}: "
                         "the fine-tuned models take the data's (it places the CDiT's landing rays, no weights change)")
    return notes


def view_of(data: Path, dirs: list[dict], dest: Path, index: dict, split: str) -> None:
    """A suite folder over some of `data`'s trajectories: real folders of links, so that
    `worldpack plan` writes its files here and never into the user's dataset."""
    dest.mkdir(parents=True, exist_ok=True)
    for t in dirs:
        d = dest / t["dir"]
        d.mkdir(exist_ok=True)
        for name in TRAJECTORY_FILES:
            src = (data / t["dir"] / name).resolve()
            if src.exists() and not (d / name).exists():
                (d / name).symlink_to(src)
    view = {**index, "trajectories": dirs, "split": split, "total_frames": sum(t["frames"] for t in dirs)}
    (dest / "index.json").write_text(json.dumps(view, indent=2))


def split_stage(run: Run) -> dict:
    index = json.loads((run.data / "index.json").read_text())
    trajs = index["trajectories"]
    held = run.settings["heldout"]
    train_dir, held_dir = run.work / "data" / "train", run.work / "data" / "heldout"
    if held["folder"]:
        held_src = Path(held["folder"])
        run.worldpack("check", "--data", str(held_src))
        view_of(run.data, trajs, train_dir, index, "train")
        hindex = json.loads((held_src / "index.json").read_text())
        view_of(held_src, hindex["trajectories"], held_dir, hindex, "heldout")
        chosen = [t["dir"] for t in hindex["trajectories"]]
    else:
        picked = budget.heldout_picks(len(trajs), held)
        view_of(run.data, [t for i, t in enumerate(trajs) if i not in picked], train_dir, index, "train")
        view_of(run.data, [t for i, t in enumerate(trajs) if i in picked], held_dir, index, "heldout")
        chosen = [trajs[i]["dir"] for i in sorted(picked)]
    run.worldpack("plan", "--data", str(train_dir), "--memory-need")
    run.worldpack("plan", "--data", str(held_dir))
    return {"heldout": chosen, "train_trajectories": len(json.loads((train_dir / "index.json").read_text())["trajectories"])}


def set_focal(run_dir: Path, focal: float) -> None:
    cfg = json.loads((run_dir / "config.json").read_text())
    if cfg["cdit"].get("landing_depths"):
        cfg["cdit"]["focal"] = focal
    (run_dir / "config.json").write_text(json.dumps(cfg, indent=2))


def link(target: Path, name: Path) -> None:
    if not name.exists() and not name.is_symlink():
        name.symlink_to(target.resolve())


def from_stage(run: Run, focal: float) -> dict:
    """The starting weights: the family's three models rebuilt from their graphs (checked
    against their references), or, from scratch, a fresh configuration."""
    fam = run.settings["from"]
    w = run.work
    if fam is None:
        from_scratch_config(w / "ae", focal)
        return {"from": "scratch"}
    for role in ("teacher", "baseline"):
        if not any((w / f"from-{role}").glob("cdit-*.pt")):
            recover(Path(fam[role]), w / f"from-{role}", None)
    student = w / "student"
    if not (student / "distilled-worldpack-1.pt").exists():
        shutil.rmtree(student, ignore_errors=True)
        recover(Path(fam["teacher"]), student, "worldpack")
        recover(Path(fam["served"]), student, "worldpack")
    (w / "ae").mkdir(exist_ok=True)
    if not (w / "ae" / "autoencoder.pt").exists():
        shutil.copy(w / "from-teacher" / "config.json", w / "ae" / "config.json")
        shutil.copy(w / "from-teacher" / "autoencoder.pt", w / "ae" / "autoencoder.pt")
    for d in (w / "ae", student):
        set_focal(d, focal)
    start = int(torch.load(student / "distilled-worldpack-1.pt", map_location="cpu", weights_only=False)["step"])
    return {"from": fam, "digests": {role: folder_digest(Path(f)) for role, f in fam.items()}, "student_start_step": start}


def from_scratch_config(ae_dir: Path, focal: float) -> None:
    ae_dir.mkdir(parents=True, exist_ok=True)
    if not (ae_dir / "config.json").exists():
        cfg = ModelConfig()
        cfg.cdit.landing_depths = (2.0, 6.0, 20.0)
        cfg.cdit.focal = focal
        (ae_dir / "config.json").write_text(json.dumps(cfg.to_json(), indent=2))


def share_autoencoder(run: Run, run_dir: Path) -> None:
    """Every denoiser trains in the one fine-tuned autoencoder's latent space."""
    for name in ("autoencoder.pt", "latents"):
        p = run_dir / name
        if p.exists() and not p.is_symlink():
            p.unlink() if p.is_file() else shutil.rmtree(p)
        link(run.work / "ae" / name, p)


def prepare_run(run: Run, run_dir: Path, config_from: Path, focal: float) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    if not (run_dir / "config.json").exists():
        shutil.copy(config_from / "config.json", run_dir / "config.json")
        set_focal(run_dir, focal)
    share_autoencoder(run, run_dir)


def autoencoder_stage(run: Run, minutes: float) -> dict:
    s, ae = run.settings["autoencoder"], run.work / "ae"
    train_split = run.work / "data" / "train"
    start = int(torch.load(ae / "autoencoder.pt", map_location="cpu")["step"]) if (ae / "autoencoder.pt").exists() else 0
    record = run.stage("autoencoder")
    origin = record.setdefault("start_step", start)
    train_autoencoder(train_split, ae, origin + s["steps"], s["batch"], s["lr"], run.settings["device"], minutes)
    encode(train_split, ae, run.settings["device"])
    return {"steps_from": origin}


def recipe_of(s: dict) -> Recipe:
    return Recipe(context_noise=s.get("context_noise", 0.7), generated_level=s.get("generated_level", 0.3))


def baseline_stage(run: Run, focal: float, minutes: float) -> dict:
    s, w = run.settings["baseline"], run.work
    fam = run.settings["from"]
    prepare_run(run, w / "baseline", w / ("from-baseline" if fam else "ae"), focal)
    init = next((w / "from-baseline").glob("cdit-*.pt")) if fam else None
    train_cdit(w / "data" / "train", w / "baseline", "baseline", s["steps"], s["batch"], s["lr"], s["ema"],
               run.settings["device"], minutes, init, 0.0, recipe_of(run.settings["teacher"]))
    return {"init_from": str(init) if init else None}


def teacher_stage(run: Run, focal: float, minutes: float) -> dict:
    """WorldPack with the warp input, the 10-step model: fine-tuned from the family's, or
    from this run's baseline (the paper's order)."""
    s, w = run.settings["teacher"], run.work
    fam = run.settings["from"]
    prepare_run(run, w / "teacher", w / ("from-teacher" if fam else "ae"), focal)
    init = w / "from-teacher" / "cdit-worldpack.pt" if fam else w / "baseline" / "cdit-baseline.pt"
    train_cdit(w / "data" / "train", w / "teacher", "worldpack", s["steps"], s["batch"], s["lr"], s["ema"],
               run.settings["device"], minutes, init, s["memory_focus"], recipe_of(s), warp=True)
    return {"init_from": str(init)}


def student_stage(run: Run, minutes: float, adversarial: bool = False) -> dict:
    """The 1-step student distilled from the fine-tuned teacher's 10 DDIM steps, continuing
    the family's student (or the teacher's weights, from scratch)."""
    s, w = run.settings["student"], run.work
    student = w / "student"
    student.mkdir(exist_ok=True)
    if not (student / "config.json").exists():
        shutil.copy(w / "teacher" / "config.json", student / "config.json")
    share_autoencoder(run, student)
    shutil.copy(w / "teacher" / "cdit-worldpack.pt", student / "cdit-worldpack.pt")
    start = run.lineage["stages"]["from"].get("student_start_step", 0)
    a = run.settings["adversarial"]
    if adversarial:
        start = run.lineage["stages"]["student"]["final_step"]
        steps = start + a.get("steps", 2000)
    else:
        steps = start + s["steps"]
    distill(w / "data" / "train", student, "worldpack", "999", s["teacher_steps"], steps, s["batch"], s["lr"], s["ema"],
            run.settings["device"], minutes,
            adversarial_weight=a["weight"] if adversarial else 0.0, adversarial_start=a["start"],
            adversarial_cap=a["cap"] if adversarial else None)
    final = int(torch.load(student / "distilled-worldpack-1.pt", map_location="cpu", weights_only=False)["step"])
    return {"steps_from": start, "final_step": final}


def heads_stage(run: Run) -> dict:
    """The fusion head on this world: the bare student's own frames beside their fused warp
    (`worldpack fusion-data` on the training walks), a head trained on them from the family's
    kept head, then the rule that takes the warp's detail where head and warp agree."""
    w, h, fam = run.work, run.settings["heads"], run.settings["from"]
    train_split, bare, folder = w / "data" / "train", w / "student-bare", w / "heads"
    if not (bare / "manifest.json").exists():
        export(w / "student", "worldpack", ["worldpack"], w / "data" / "heldout", bare, "cpu", True, distilled=1,
               warp_data=(train_split,))
        set_warp_frames(bare, run.settings["serving"]["warp_frames"])
    if not (folder / "data" / "truth.npy").exists():
        # At most `heads.walks` of the training walks, spread over the suite, so that the
        # data's minutes stay within what the budget set aside for them.
        index = json.loads((train_split / "index.json").read_text())
        view_of(run.data, budget.spread(index["trajectories"], h["walks"]), w / "data" / "heads", index, "heads")
        run.worldpack("fusion-data", "--suite", str(w / "data" / "heads"), "--model", str(bare), "--stride", str(h["stride"]),
                      "--threads", str(run.settings["threads"]), "--out", str(folder / "data"))
    init = Path(fam["served"]) if fam and has_head(Path(fam["served"])) else None
    fusion.train([folder / "data"], folder / "kept", h["steps"], h["batch"], h["lr"], h["minutes"], 24, edge_weight=1.0,
                 init_from=init)
    fusion.export(folder / "kept", bare, folder / "model", folder / "data")
    if h["warp_detail"]:
        fusion.pair(folder / "model", folder / "model", folder / "model", folder / "data", warp_detail=h["warp_detail"])
    scores = json.loads((folder / "kept" / "fusion-held-out.json").read_text())["scores"]
    return {"init_from": str(init) if init else None, "held_out": scores}


def export_stage(run: Run) -> dict:
    w, out, fam = run.work, run.out, run.settings["from"]
    held, more = w / "data" / "heldout", (w / "data" / "train",)
    half = True
    export(w / "baseline", "baseline", ["baseline"], held, out / "baseline", "cpu", half, warp_data=more)
    export(w / "teacher", "worldpack", ["worldpack"], held, out / "teacher", "cpu", half, warp_data=more,
           fusion_from=Path(fam["teacher"]) if fam and has_head(Path(fam["teacher"])) else None)
    # The served model: the student with the head trained on this world's frames.
    served = w / "heads" / "model"
    for p in served.iterdir():
        if p.is_dir():
            shutil.copytree(p, out / p.name, dirs_exist_ok=True)
        else:
            shutil.copy(p, out / p.name)
    rename_model(out, served.name, out.name)
    return {"outputs": {p: folder_digest(out / p) for p in ("baseline", "teacher")}}


def rename_model(folder: Path, old: str, new: str) -> None:
    """A model folder's name in its manifest, and where its head pair names itself."""
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["name"] = new
    for part in manifest.get("fusion", {}).get("pair", {}).values():
        if isinstance(part, dict) and part.get("model") == old:
            part["model"] = new
    (folder / "manifest.json").write_text(json.dumps(manifest, indent=1))


def has_head(model: Path) -> bool:
    return "fusion" in json.loads((model / "manifest.json").read_text())


def graph_files(manifest: dict) -> dict[str, str]:
    files = {"encoder": manifest["autoencoder"]["encoder"]["file"], "decoder": manifest["autoencoder"]["decoder"]["file"]}
    files.update({f"denoiser_{lay['name']}": lay["file"] for lay in manifest["denoiser"]["layouts"]})
    if "fusion" in manifest:
        files["fusion"] = manifest["fusion"]["file"]
    return files


def parity(model: Path) -> float:
    """Every graph through ONNX Runtime against the outputs PyTorch wrote at export: the
    largest difference over the tolerance's bound (at most 1 passes)."""
    manifest = json.loads((model / "manifest.json").read_text())
    tol = manifest["reference"]["tolerance"]
    worst = 0.0
    for graph, file in graph_files(manifest).items():
        ref = model / manifest["reference"]["graphs"][graph]
        session = ort.InferenceSession(str(model / file), providers=["CPUExecutionProvider"])
        feed = {i.name: np.load(ref / f"{i.name}.npy") for i in session.get_inputs()}
        for o, got in zip(session.get_outputs(), session.run(None, feed)):
            want = np.load(ref / f"{o.name}.npy")
            worst = max(worst, float((np.abs(got - want) / (tol["abs"] + tol["rel"] * np.abs(want))).max()))
    return worst


def parity_stage(run: Run) -> dict:
    scores = {}
    for name, folder in (("served", run.out), ("baseline", run.out / "baseline"), ("teacher", run.out / "teacher")):
        scores[name] = parity(folder)
        print(f"parity {name}: largest difference {scores[name]:.3f} of the tolerance", flush=True)
        if scores[name] > 1.0:
            raise StageFailed(f"{folder}: ONNX Runtime differs from the PyTorch references by {scores[name]:.2f} "
                              "times the tolerance; rerun the export stage (delete its entry in lineage.json)")
    return {"tolerance_used": scores}


def eval_stage(run: Run) -> dict:
    """Rollouts on the held-out split: the served configuration against the model it
    started from, its own 4-frame baseline and the references (depth reprojection, the fused warp)."""
    w, fam, e = run.work, run.settings["from"], run.settings["eval"]
    models = w / "eval" / "models"
    models.mkdir(parents=True, exist_ok=True)
    link(run.out / "baseline", models / "baseline")
    # The strip's first row picks its walk: the median one of (that row − the served model).
    rows = (["started_from_covisible"] if fam else []) + ["served_covisible", "baseline"]
    args = ["eval", "--suite", str(w / "data" / "heldout"), "--models", str(models), "--policies", "baseline",
            "--extra", f"served={run.out}", "--covisible", "served",
            "--probe-frames", str(run.settings["serving"]["warp_frames"]), "--against", "served_covisible",
            "--threads", str(e["threads"]), "--out", str(w / "eval"), "--strip", ",".join(rows)]
    if fam:
        args += ["--extra", f"started_from={fam['served']}", "--covisible", "started_from"]
    for row in rows:  # the references (reproject, the fused warp) always run
        args += ["--only", row]
    if e.get("limit"):
        args += ["--limit", str(e["limit"])]
    run.worldpack(*args)
    return {"results": str(w / "eval" / "results.json")}


def adversarial_stage(run: Run, minutes: float) -> dict | None:
    """ADD's adversarial term: pays off only at a GPU's throughput; on CPU the model goes without."""
    if run.settings["device"] != "cuda":
        print("adversarial: skipped on CPU. Without it the student is distilled by regression alone: on the voxel "
              "world that kept 0.56 of the truth's edge energy against 0.75 with it (docs/model.md); give --device "
              "cuda to run it", flush=True)
        return None
    return student_stage(run, minutes, adversarial=True)


def card_stage(run: Run) -> dict:
    manifest = json.loads((run.out / "manifest.json").read_text())
    manifest["serving"] = run.settings["serving"]
    # The day it was made and its settings: two models of one folder name are told apart by it.
    manifest["version"] = f"{time.strftime('%Y-%m-%d')}+{wsettings.digest(run.settings)[:8]}"
    manifest["lineage"] = {"settings_digest": wsettings.digest(run.settings), "data": run.lineage["stages"]["check"]["data"],
                           "stages": {k: {"minutes": round(v["minutes"], 1), "status": v["status"]}
                                      for k, v in run.lineage["stages"].items()}}
    results = json.loads((run.work / "eval" / "results.json").read_text())
    manifest["heldout_eval"] = card.summarise(results)
    (run.out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    strip = run.work / "eval" / "strip.png"
    if strip.exists():
        shutil.copy(strip, run.out / "heldout-strip.png")
    (run.out / "MODEL.md").write_text(card.render(manifest, run.settings, run.lineage))
    return {"card": "MODEL.md"}


def stages(run: Run, facts: dict) -> list:
    """(name, what it does, the work) in order; training stages take their minutes."""
    f = facts["focal"]
    return [
        ("split", "a held-out split and the memory plans", lambda: split_stage(run)),
        ("from", "the starting weights", lambda: from_stage(run, f)),
        ("autoencoder", "the autoencoder trained on these frames (from the family's, if any), then the latent cache",
         lambda: autoencoder_stage(run, run.training_minutes("autoencoder"))),
        ("baseline", "the 4-frame baseline", lambda: baseline_stage(run, f, run.training_minutes("baseline"))),
        ("teacher", "WorldPack with the warp input (10 DDIM steps)", lambda: teacher_stage(run, f, run.training_minutes("teacher"))),
        ("student", "the 1-step student distilled from it", lambda: student_stage(run, run.training_minutes("student"))),
        ("adversarial", "the student against a discriminator (GPU only)",
         lambda: adversarial_stage(run, run.training_minutes("adversarial"))),
        ("heads", "the fusion head retrained on this world's frames", lambda: heads_stage(run)),
        ("export", "ONNX graphs, manifests and references", lambda: export_stage(run)),
        ("parity", "ONNX Runtime against the PyTorch references", lambda: parity_stage(run)),
        ("eval", "rollouts on the held-out split", lambda: eval_stage(run)),
        ("card", "the model card (MODEL.md) and how it is served", lambda: card_stage(run)),
    ]


def stop(signum, frame) -> None:
    raise KeyboardInterrupt


def make(data: Path, out: Path, source: str | None, hours: float | None, device: str | None, heldout: Path | None,
         binary: Path, repo: Path, overrides: dict | None = None) -> None:
    data = data.resolve()
    if (out / "train.json").exists():
        # Settings a newer trainer added take their defaults; train.json is rewritten with them below.
        settings = wsettings.merge(wsettings.DEFAULTS, json.loads((out / "train.json").read_text()))
        # The budget may change on a resume: stages not yet done share the new one.
        if hours is not None and hours != settings["hours"]:
            print(f"the budget changes from {settings['hours']} h to {hours} h; stages not yet done take their "
                  "shares of the new one")
            settings["hours"] = hours
            wsettings.check(settings)
        changed = {"device": device} if device is not None and device != settings["device"] else {}
        if changed or (source and not wsettings.same_family(settings["from"], wsettings.family(source, repo))):
            raise SystemExit(f"--out: {out} was started with other settings ({changed or '--from'}); run the same "
                             "command to resume it, or choose another --out")
        if Path(settings.get("data", "")).resolve() != data:
            raise SystemExit(f"--data: {out} was trained on {settings.get('data')}, not {data}")
    else:
        settings = wsettings.initial(source, 2.0 if hours is None else hours, device or "cpu", repo, overrides)
        settings["data"] = os.path.relpath(data)
        if heldout is not None:
            settings["heldout"]["folder"] = os.path.relpath(heldout)
        wsettings.check(settings)
        if out.exists() and any(out.iterdir()):
            raise SystemExit(f"--out: {out} is not empty and holds no train.json; choose a new folder")
    facts = check_data(data, binary, settings)
    notes = check_family(settings, facts["focal"])
    # Nothing is written before the checks pass.
    out.mkdir(parents=True, exist_ok=True)
    (out / "train.json").write_text(json.dumps(settings, indent=2))
    signal.signal(signal.SIGTERM, stop)
    with open(out / "train.log", "a") as log:
        sys.stdout, sys.stderr = Tee(sys.__stdout__, log), Tee(sys.__stderr__, log)
        try:
            drive(Run(out, data, binary, repo), facts, notes)
        finally:
            sys.stdout, sys.stderr = sys.__stdout__, sys.__stderr__


def print_budget(run: Run) -> None:
    """How the budget divides, before any stage runs: a large dataset's fixed work is seen
    before it has taken the training's minutes."""
    stages, total, ahead = run.lineage["stages"], run.settings["hours"] * 60, run.work_ahead()
    spent = budget.spent(stages)
    if not any(budget.pending(stages, name) for name in stages):
        print(f"budget {total:.0f} min: {spent:.0f} spent, every stage done", flush=True)
        return
    training = bool(budget.open_training(stages))
    pool = budget.training_pool(run.settings, stages, ahead) if training else 0.0
    parts = ", ".join(f"{k} {v:.0f}" for k, v in ahead.items() if v >= 0.5)
    print(f"budget {total:.0f} min: {spent:.0f} spent, about {sum(ahead.values()):.0f} set aside for the work that is "
          f"not training ({parts}), {pool:.0f} for training", flush=True)
    if training and pool < 0.3 * total:
        print("note: the work sized by the dataset leaves training under a third of the budget; give more --hours, "
              "or fewer walks to it (--set heads.walks=N, --set heldout.at_most=N)", flush=True)


def drive(run: Run, facts: dict, notes: list[str]) -> None:
    torch.set_num_threads(run.settings["threads"])
    # The ONNX exporter's note, at every export, that torchvision's operators are not registered.
    logging.getLogger("torch.onnx._internal.exporter._registration").setLevel(logging.ERROR)
    checked = run.stage("check")  # first: it ran before anything was written
    checked.update(status="done", data={"suite": os.path.relpath(run.data), "digest": suite_digest(run.data),
                                        **{k: facts[k] for k in ("trajectories", "frames", "kind", "focal")}}, notes=notes)
    run.save()
    for line in notes:
        print(f"note: {line}")
    plan = stages(run, facts)
    for name, _, _ in plan:
        run.stage(name)  # the lineage lists the stages in the order they run
    print_budget(run)
    for i, (name, what, work) in enumerate(plan, 1):
        record = run.stage(name)
        if record["status"] in ("done", "skipped"):
            print(f"[{i}/{len(plan)}] {name}: {record['status']} ({record['minutes']:.1f} min), kept", flush=True)
            continue
        total, spent = run.settings["hours"] * 60, budget.spent(run.lineage["stages"])
        minutes = run.training_minutes(name) if name in budget.TRAINING_STAGES else None
        left = run.training_pool() if budget.open_training(run.lineage["stages"]) else 0.0
        print(f"[{i}/{len(plan)}] {name}: {what}" + (f" (budget {minutes:.0f} min)" if minutes is not None else "")
              + f"; training left at most {left:.0f} min; {spent:.0f} of the budget's {total:.0f} min spent, "
              f"about {max(0.0, total - spent):.0f} to go",
              flush=True)
        t0 = time.time()
        try:
            result = work()
        except KeyboardInterrupt:
            # Stopped (Ctrl-C or SIGTERM): the minutes count against the stage's share when it resumes.
            record["minutes"] += (time.time() - t0) / 60
            record["status"] = "stopped"
            run.save()
            raise SystemExit(f"worldpack train: stopped in stage `{name}`; run the same command again to resume it")
        except (Exception, SystemExit) as e:
            if not isinstance(e, (StageFailed, SystemExit)):
                traceback.print_exc()  # into the log: a fault of the trainer's, not of the input
            record["minutes"] += (time.time() - t0) / 60
            record["status"], record["error"] = "failed", str(e)
            run.save()
            raise SystemExit(f"worldpack train: stage `{name}` failed: {e}\n"
                             f"Finished stages are kept; fix the cause and run the same command again to resume "
                             f"from `{name}` (log: {run.out / 'train.log'}).")
        record["minutes"] += (time.time() - t0) / 60
        record["status"] = "skipped" if result is None else "done"
        record.pop("error", None)
        record.update(result or {})
        run.save()
    print(f"done: {run.out} (serve it: worldpack serve --model {run.out}; its card: {run.out / 'MODEL.md'})")
