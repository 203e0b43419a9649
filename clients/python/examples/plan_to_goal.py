"""Goal-image navigation by planning over imagined futures, through the API.

As Navigation World Models evaluates it: a start and a goal view of one
world; the agent plans by the cross-entropy method over candidate action
sequences imagined from its present (`imagine`), takes the first action in
the real world (an observing step: the voxel world's own frame), re-plans,
and stops when its view matches the goal. Success is judged by pose: the
stop within `--reach` blocks and `--turn` degrees of the goal's.

    ./scripts/serve.sh &                                                # the served model
    python clients/python/examples/plan_to_goal.py --out runs/plan/served.json
    python clients/python/examples/plan_to_goal.py --policy random --out runs/plan/random.json
    python clients/python/examples/plan_to_goal.py --policy truth --out runs/plan/truth.json    # the ceiling
    worldpack serve --model fixtures/variants/baseline --policy baseline --addr 127.0.0.1:8081 &
    python clients/python/examples/plan_to_goal.py --url http://127.0.0.1:8081 --out runs/plan/baseline.json
    python clients/python/examples/plan_to_goal.py --compare runs/plan/served.json runs/plan/random.json

Needs the client and the project's metrics (`pip install --no-deps -e train`: numpy only).

Episodes (world seed `--first-world + e`): the agent looks round where it
starts (12 turns of 30°, observed), then walks out `--out-steps` steps with
small turns (observed). Half the goals were seen on the way out (the view
from the start, before the walk: memory holds it); the other half were not
(the view from the start looking the other way, taken on a throwaway fork
whose frames the session never sees; the look-round is then skipped), so
what the model imagines there is its own guess.

`--policy truth` plans with the world's renderer as its model: each
candidate is a fork of the session stepped by observing steps (the world's
true frames), then deleted. `--policy random` takes uniformly random actions.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from worldpack_client import Client
from worldpack_train.metrics import psnr

# The planner's actions: one key or a turn of 15° per step.
ACTIONS = [{"forward": True}, {"back": True}, {"left": True}, {"right": True}, {"yaw_deg": 15.0}, {"yaw_deg": -15.0}]


def yaw_of(pose: dict) -> float:
    """Heading in the horizontal plane (degrees) of an answered pose's optical axis."""
    r = np.asarray(pose["rotation"], float)
    return float(np.degrees(np.arctan2(r[0][2], r[2][2])))


def apart(a: dict, b: dict) -> tuple[float, float]:
    """Horizontal distance (blocks) and heading difference (degrees) of two answered poses."""
    pa, pb = np.asarray(a["position"]), np.asarray(b["position"])
    turn = abs((yaw_of(a) - yaw_of(b) + 180.0) % 360.0 - 180.0)
    return float(np.hypot(*(pa - pb)[[0, 2]])), turn


def episode_start(c: Client, world: int, seen: bool, out_steps: int, rng: np.random.Generator):
    """A session that has looked round (when the goal was seen) and walked out; the goal's image and pose."""
    s = c.create_session(synthetic_seed=world)
    goal_session = c.fork(s) if not seen else None
    if seen:
        for _ in range(12):
            c.step(s, {"yaw_deg": 30.0}, observe=True)
    goal_index = c.session(s)["frames"] - 1
    for i in range(out_steps):
        # Turns of the planner's own 15°, so that the way back can be walked exactly.
        c.step(s, {"forward": True, "yaw_deg": float(rng.choice([-15.0, 15.0])) if i % 3 == 2 else 0.0}, observe=True)
    if seen:
        goal_image, goal_pose = c.frame_image(s, goal_index), c.frame(s, goal_index)["pose"]
    else:
        # The start's view turned round, on a fork deleted at once: never in the session's memory.
        for _ in range(6):
            last = c.step(goal_session, {"yaw_deg": 30.0}, observe=True)
        goal_image, goal_pose = last.image, last.raw["pose"]
        c.delete_session(goal_session)
    return s, goal_image, goal_pose


def cem(c: Client, s: int, goal: np.ndarray, a, rng: np.random.Generator) -> tuple[int, float]:
    """The first action of the best sequence the cross-entropy method finds (index into ACTIONS), and its score."""
    probs = np.full((a.horizon, len(ACTIONS)), 1.0 / len(ACTIONS))
    best, best_score = None, -np.inf
    for _ in range(a.iterations):
        seqs = np.array([[rng.choice(len(ACTIONS), p=p) for p in probs] for _ in range(a.candidates)])
        scores = score(c, s, goal, seqs, a)
        order = np.argsort(-scores)
        if scores[order[0]] > best_score:
            best, best_score = seqs[order[0]], float(scores[order[0]])
        elites = seqs[order[: a.elites]]
        probs = np.stack([np.bincount(elites[:, h], minlength=len(ACTIONS)) + 0.5 for h in range(a.horizon)])
        probs /= probs.sum(axis=1, keepdims=True)
    return int(best[0]), best_score


def score(c: Client, s: int, goal: np.ndarray, seqs: np.ndarray, a) -> np.ndarray:
    """Each sequence's last frame against the goal, higher is closer: imagined by the
    served model, or (`--policy truth`) observed in the world on a fork."""
    if a.policy == "truth":
        out = []
        for seq in seqs:
            f = c.fork(s)
            for i in seq:
                last = c.step(f, ACTIONS[i], observe=True)
            c.delete_session(f)
            out.append(psnr(last.image, goal))
        return np.array(out)
    plans = [[ACTIONS[i] for i in seq] for seq in seqs]
    r = c.imagine(s, plans, seed=a.seed, frames="none", goal=goal, steps=a.sampler_steps)
    if a.score == "latent":
        return np.array([-ro.goal["latent_mse"] for ro in r.rollouts])
    return np.array([ro.goal["psnr_db"] for ro in r.rollouts])


def run_episode(c: Client, e: int, a) -> dict:
    rng = np.random.default_rng(a.first_world + e)
    seen = e % 2 == 0
    s, goal, goal_pose = episode_start(c, a.first_world + e, seen, a.out_steps, rng)
    start_pose = c.frame(s, c.session(s)["frames"] - 1)["pose"]
    view = c.frame_image(s, c.session(s)["frames"] - 1)
    pose, steps, decide_s, stopped = start_pose, 0, [], False
    while steps < a.max_steps:
        if psnr(view, goal) >= a.stop_db:
            stopped = True
            break
        t = time.perf_counter()
        if a.policy == "random":
            choice = int(rng.integers(len(ACTIONS)))
        else:
            choice, _ = cem(c, s, goal, a, rng)
        decide_s.append(time.perf_counter() - t)
        r = c.step(s, ACTIONS[choice], observe=True)
        view, pose, steps = r.image, r.raw["pose"], steps + 1
    reach, turn = apart(pose, goal_pose)
    start_reach, start_turn = apart(start_pose, goal_pose)
    c.delete_session(s)
    return {"episode": e, "world": a.first_world + e, "goal_seen": seen, "stopped": stopped, "steps": steps,
            "success": bool(stopped and reach <= a.reach and turn <= a.turn), "final_blocks": reach, "final_deg": turn,
            "start_blocks": start_reach, "start_deg": start_turn, "final_psnr_db": psnr(view, goal),
            "decide_s_median": float(np.median(decide_s)) if decide_s else 0.0}


def bootstrap(diff: np.ndarray, draws: int = 10000, seed: int = 0) -> tuple[float, float, float]:
    """Mean of paired differences over episodes and its 95% percentile-bootstrap interval."""
    rng = np.random.default_rng(seed)
    means = diff[rng.integers(0, len(diff), (draws, len(diff)))].mean(axis=1)
    return float(diff.mean()), float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def summary(rows: list[dict]) -> str:
    lines = []
    for name, sel in [("all", rows), ("goal seen", [r for r in rows if r["goal_seen"]]), ("goal unseen", [r for r in rows if not r["goal_seen"]])]:
        if sel:
            lines.append(f"{name:<12} success {np.mean([r['success'] for r in sel]):.2f} of {len(sel)}, steps {np.mean([r['steps'] for r in sel]):.1f}, "
                         f"final {np.mean([r['final_blocks'] for r in sel]):.2f} blocks / {np.mean([r['final_deg'] for r in sel]):.0f}°")
    return "\n".join(lines)


def compare(a_path: str, b_path: str) -> None:
    a, b = (json.loads(Path(p).read_text()) for p in (a_path, b_path))
    by = {r["episode"]: r for r in b["episodes"]}
    pairs = [(r, by[r["episode"]]) for r in a["episodes"] if r["episode"] in by]
    print(f"{a['label']} − {b['label']}, paired over {len(pairs)} episodes (mean [95% interval]):")
    for what, key in [("success", "success"), ("steps", "steps"), ("final distance (blocks)", "final_blocks")]:
        m, lo, hi = bootstrap(np.array([float(x[key]) - float(y[key]) for x, y in pairs]))
        print(f"  {what:<24} {m:+.2f} [{lo:+.2f}, {hi:+.2f}]")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", default="http://127.0.0.1:8080")
    ap.add_argument("--policy", choices=["model", "random", "truth"], default="model",
                    help="plan with the server's model, act at random, or plan with the world's renderer")
    ap.add_argument("--episodes", type=int, default=8)
    ap.add_argument("--first-world", type=int, default=100, help="episode e is in synthetic world first-world + e")
    ap.add_argument("--out-steps", type=int, default=6, help="steps walked out before the agent plans its way to the goal")
    ap.add_argument("--max-steps", type=int, default=20)
    ap.add_argument("--candidates", type=int, default=6)
    ap.add_argument("--horizon", type=int, default=2)
    ap.add_argument("--iterations", type=int, default=2)
    ap.add_argument("--elites", type=int, default=3)
    ap.add_argument("--score", choices=["psnr", "latent"], default="psnr", help="the imagined last frame against the goal")
    ap.add_argument("--sampler-steps", type=int, default=None)
    ap.add_argument("--stop-db", type=float, default=22.0, help="stop when the view's PSNR against the goal reaches this")
    ap.add_argument("--reach", type=float, default=0.5, help="success: within this many blocks of the goal's position")
    ap.add_argument("--turn", type=float, default=20.0, help="and this many degrees of its heading")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--label", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"))
    a = ap.parse_args()
    if a.compare:
        compare(*a.compare)
        return
    c = Client(a.url)
    label = a.label or f"{a.policy} @ {a.url}"
    rows = []
    for e in range(a.episodes):
        r = run_episode(c, e, a)
        rows.append(r)
        print(f"episode {e:2d} world {r['world']} goal {'seen' if r['goal_seen'] else 'unseen':<6} {'success' if r['success'] else 'miss   '} "
              f"in {r['steps']:2d} steps; {r['start_blocks']:.2f} → {r['final_blocks']:.2f} blocks, {r['start_deg']:.0f} → {r['final_deg']:.0f}°, "
              f"decision {r['decide_s_median']:.2f} s")
    print(summary(rows))
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps({"label": label, "settings": {k: v for k, v in vars(a).items() if k not in ("compare", "out")},
                                           "episodes": rows}, indent=1))
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
