"""The trainer's settings: one JSON file written into the output folder
(`train.json`), made from the defaults of the dataset's world kind and the
command's flags, then read back on every rerun so that a resumed run trains
with what it started with."""

from __future__ import annotations

import copy
import hashlib
import json
import os
from pathlib import Path

FORMAT = "worldpack-train/1"

# The shipped model families `--from` can name: the served 1-step student, the
# 10-step geometry model it was distilled from, and the 4-frame baseline beside it.
FAMILIES = {
    "voxel": {"served": "fixtures/variants/worldpack_geometry_fused_1step",
              "teacher": "fixtures/variants/worldpack_geometry_fused",
              "baseline": "fixtures/variants/baseline"},
    "doom": {"served": "fixtures/doom/geometry_fused",
             "teacher": "fixtures/doom/geometry_fused_10step",
             "baseline": "fixtures/doom/baseline"},
}

# How the training stages share the minutes the budget leaves them (see `COSTS`). On a GPU
# the adversarial student takes part of the student's share; on a CPU it is skipped.
BUDGET_SHARES = {"autoencoder": 0.10, "baseline": 0.22, "teacher": 0.38, "student": 0.30, "adversarial": 0.0}
BUDGET_SHARES_CUDA = {**BUDGET_SHARES, "student": 0.18, "adversarial": 0.12}

# What the work that is not training costs, measured on a 2-core machine (one thread per
# stage, other work on the second core). The budget sets these minutes aside first, sized
# by the dataset, and the training stages share the rest; a faster machine finishes early.
COSTS = {
    "fixed_minutes": 6.0,         # split and plans, the starting weights, the exports, parity, card
    "encode_ms_per_frame": 12.0,  # the latent cache: every training frame through the encoder
    "head_data_ms_per_frame": 10.0,  # `worldpack fusion-data` over the head's walks
    "eval_ms_per_frame": 110.0,   # `worldpack eval`: five rows rolled out over the held-out walks
}


def budget_shares(device: str) -> dict:
    return BUDGET_SHARES_CUDA if device == "cuda" else BUDGET_SHARES

DEFAULTS = {
    "format": FORMAT,
    "from": None,            # a family ({served, teacher, baseline} folders) or null: from scratch
    "device": "cpu",
    "hours": 2.0,            # the whole command's budget, data made beforehand not counted
    "threads": 1,            # torch threads for the training stages
    # Held out for the card: a share of the walks, within bounds (the eval's minutes grow with them).
    "heldout": {"share": 0.1, "at_least": 1, "at_most": 24, "folder": None},
    "autoencoder": {"steps": 1500, "batch": 32, "lr": 3e-4},
    "baseline": {"steps": 3000, "batch": 32, "lr": 1e-4, "ema": 0.999},
    "teacher": {"steps": 4000, "batch": 32, "lr": 1e-4, "ema": 0.999, "memory_focus": 0.5,
                "context_noise": 0.7, "generated_level": 0.3},
    "student": {"steps": 2000, "batch": 16, "lr": 1e-4, "ema": 0.998, "teacher_steps": 10},
    # The fusion head retrained on the student's own frames of this world (MSE + edges, from the
    # family's kept head), then the warp's luma detail taken where the two agree (T in 8-bit levels).
    # Its examples come from at most `walks` training walks, spread over the suite.
    "heads": {"steps": 1500, "batch": 32, "lr": 1e-3, "stride": 2, "warp_detail": 2.0, "minutes": 8.0, "walks": 96},
    # The adversarial term (ADD) only pays off with a GPU's throughput: skipped on CPU.
    "adversarial": {"weight": 0.5, "start": 200, "cap": 0.1},
    "serving": {"policy": "worldpack", "method": "ddim", "steps": 1, "covisible": True, "warp_frames": 32},
    "eval": {"limit": None, "threads": 1},
}

# From scratch nothing is fine-tuned: longer schedules and larger learning rates.
FROM_SCRATCH = {
    "autoencoder": {"steps": 6000, "lr": 1e-3},
    "baseline": {"steps": 12000, "lr": 3e-4},
    "teacher": {"steps": 8000, "lr": 3e-4},
    "student": {"steps": 4000},
}


def merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def family(source: str, root: Path) -> dict:
    """`--from voxel|doom` or a model folder the trainer wrote (its teacher/ and baseline/ beside it)."""
    if source in FAMILIES:
        missing = [v for v in FAMILIES[source].values() if not (root / v / "manifest.json").exists()]
        if missing:
            raise SystemExit(f"--from {source}: no model at {root / missing[0]}; run from the repository's root")
        # Relative to where the command runs (the repository), so that train.json and the card
        # name the shipped folders, not this machine's paths.
        return {k: os.path.relpath(root / v) for k, v in FAMILIES[source].items()}
    served = Path(source)
    if not (served / "manifest.json").exists():
        raise SystemExit(f"--from: {source} is neither a shipped family ({', '.join(FAMILIES)}) nor a model folder")
    missing = [p for p in ("teacher", "baseline") if not (served / p / "manifest.json").exists()]
    if missing:
        raise SystemExit(f"--from: {served} has no {' or '.join(missing)} folder beside its model; only folders "
                         "`worldpack train` wrote, or the shipped families (voxel, doom), can be fine-tuned")
    return {"served": str(served), "teacher": str(served / "teacher"), "baseline": str(served / "baseline")}


def initial(source: str | None, hours: float, device: str, root: Path, overrides: dict | None = None) -> dict:
    s = merge(DEFAULTS, {"hours": hours, "device": device})
    if source is None:
        s = merge(s, FROM_SCRATCH)
    else:
        s["from"] = family(source, root)
    return merge(s, overrides or {})


def same_family(a: dict | None, b: dict | None) -> bool:
    """Two families name the same folders, however their paths are written."""
    resolved = lambda f: None if f is None else {k: str(Path(v).resolve()) for k, v in f.items()}
    return resolved(a) == resolved(b)


def digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:16]


def check(s: dict) -> None:
    """Refuses settings no stage could run with, naming the key."""
    if s.get("format") != FORMAT:
        raise SystemExit(f"train.json: field `format`: expected {FORMAT!r}, got {s.get('format')!r}")
    if s["device"] not in ("cpu", "cuda"):
        raise SystemExit(f"train.json: field `device`: cpu or cuda, got {s['device']!r}")
    if not (isinstance(s["hours"], (int, float)) and 0 < s["hours"] <= 1000):
        raise SystemExit(f"train.json: field `hours`: a number of hours in (0, 1000], got {s['hours']!r}")
    for stage in ("autoencoder", "baseline", "teacher", "student"):
        for key in ("steps", "batch"):
            v = s[stage][key]
            if not (isinstance(v, int) and v >= 0 if key == "steps" else isinstance(v, int) and v >= 1):
                raise SystemExit(f"train.json: field `{stage}.{key}`: a whole number"
                                 f"{' >= 0' if key == 'steps' else ' >= 1'}, got {v!r}")
    share = s["heldout"]["share"]
    if not (0 < share < 1):
        raise SystemExit(f"train.json: field `heldout.share`: between 0 and 1, got {share!r}")
    for key, v in (("heldout.at_least", s["heldout"]["at_least"]), ("heldout.at_most", s["heldout"]["at_most"]),
                   ("heads.walks", s["heads"]["walks"])):
        if not (isinstance(v, int) and v >= 1):
            raise SystemExit(f"train.json: field `{key}`: a whole number >= 1, got {v!r}")
    if s["heldout"]["at_most"] < s["heldout"]["at_least"]:
        raise SystemExit(f"train.json: field `heldout.at_most`: at least `heldout.at_least` ({s['heldout']['at_least']}), "
                         f"got {s['heldout']['at_most']}")
    if s["serving"]["steps"] != 1:
        raise SystemExit("train.json: field `serving.steps`: the trainer makes a 1-step student; 1 is the only value")


def overrides(pairs: list[str]) -> dict:
    """`--set teacher.steps=500` pairs as a nested dict (values read as JSON, else as text)."""
    out: dict = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise SystemExit(f"--set: expected KEY=VALUE, got {pair!r}")
        path = key.split(".")
        node = DEFAULTS
        for part in path:
            if not isinstance(node, dict) or part not in node:
                raise SystemExit(f"--set: no setting `{key}` (see train.json's keys)")
            node = node[part]
        try:
            parsed = json.loads(value)
        except json.JSONDecodeError:
            parsed = value
        target = out
        for part in path[:-1]:
            target = target.setdefault(part, {})
        target[path[-1]] = parsed
    return out
