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

    ./scripts/serve.sh --model fixtures/doom/geometry_fused --addr 127.0.0.1:8090 &     # Doom
    python clients/python/examples/plan_to_goal.py --world doom --url http://127.0.0.1:8090 --out runs/plan/doom.json

Needs the client and the project's metrics (`pip install --no-deps -e train`: numpy only);
`--world doom` also the Doom tool's requirements (doom/requirements.txt: vizdoom, opencv).

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
import math
import sys
import time
from pathlib import Path

import numpy as np

from worldpack_client import Client
from worldpack_client.client import png_bytes
from worldpack_train.metrics import psnr

# The planner's actions: one key or a turn of 15° per step.
ACTIONS = [{"forward": True}, {"back": True}, {"left": True}, {"right": True}, {"yaw_deg": 15.0}, {"yaw_deg": -15.0}]
# With `--stop stay` the planner may also imagine staying where it is; it stops when that is best.
STAY: dict = {}


# Per world: steps walked out, the view's PSNR against the goal at which the agent stops,
# and how close (blocks or metres) a stop must be to count.
# Doom's views change slowly with the pose, so a CEM round of 12 draws rarely holds the best
# of the 36 two-step sequences, and a view can score 30 dB against the goal's a metre away
# while one at the goal's place scores 20: there the planner scores every sequence and stops
# when staying put is the best of them, or when it comes back to where it stood (imagined
# futures a step apart differ by tenths of a dB there, so it would circle the goal). Doom
# scores in latent space: the 49 last frames undecoded keep a decision near a second.
DEFAULTS = {"voxel": {"out_steps": 6, "search": "cem", "score": "psnr", "stop": "view", "stop_db": 22.0, "stop_margin": 0.0,
                      "stop_on_return": 0, "reach": 0.5},
            "doom": {"out_steps": 6, "search": "all", "score": "latent", "stop": "stay", "stop_db": 30.0, "stop_margin": 0.0,
                     "stop_on_return": 1, "reach": 0.5}}


def yaw_of(pose: dict) -> float:
    """Heading in the horizontal plane (degrees) of an answered pose's optical axis."""
    r = np.asarray(pose["rotation"], float)
    return float(np.degrees(np.arctan2(r[0][2], r[2][2])))


class VoxelWorld:
    """The server's synthetic voxel world (episode e in world seed `--first-world + e`):
    acting is an observing step, and its renderer draws any pose, on a fork."""

    unit = "blocks"

    def __init__(self, c: Client, a):
        self.c, self.a = c, a
        self.moves = len(ACTIONS)
        self.actions = ACTIONS + ([STAY] if a.stop == "stay" else [])

    def start(self, e: int, seen: bool, rng: np.random.Generator):
        """A session that has looked round (when the goal was seen) and walked out; the goal's image and pose."""
        c, world = self.c, self.a.first_world + e
        s = c.create_session(synthetic_seed=world)
        goal_session = c.fork(s) if not seen else None
        if seen:
            for _ in range(12):
                c.step(s, {"yaw_deg": 30.0}, observe=True)
        goal_index = c.session(s)["frames"] - 1
        for i in range(self.a.out_steps):
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
        last = c.session(s)["frames"] - 1
        return s, goal_image, goal_pose, c.frame_image(s, last), c.frame(s, last)["pose"]

    def act(self, s: int, choice: int):
        r = self.c.step(s, ACTIONS[choice], observe=True)
        return r.image, r.raw["pose"]

    def imagine(self, s: int, seqs: np.ndarray, goal: np.ndarray):
        return self.c.imagine(s, [[self.actions[i] for i in seq] for seq in seqs], seed=self.a.seed, frames="none",
                              goal=goal, goal_score=goal_scoring(self.a), steps=self.a.sampler_steps)

    def rendered(self, s: int, seqs: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """Each sequence's last frame as the world draws it: a fork stepped by observation, then deleted."""
        out = []
        for seq in seqs:
            f = self.c.fork(s)
            for i in seq:
                last = self.c.step(f, self.actions[i], observe=True)
            self.c.delete_session(f)
            out.append(psnr(last.image, goal))
        return np.array(out)

    @staticmethod
    def apart(a: dict, b: dict) -> tuple[float, float]:
        """Horizontal distance (blocks) and heading difference (degrees) of two answered poses."""
        pa, pb = np.asarray(a["position"]), np.asarray(b["position"])
        turn = abs((yaw_of(a) - yaw_of(b) + 180.0) % 360.0 - 180.0)
        return float(np.hypot(*(pa - pb)[[0, 2]])), turn

    def end(self, s: int) -> None:
        self.c.delete_session(s)

    def close(self) -> None:
        pass


class DoomWorld:
    """ViZDoom on the held-out maps (episode e on map `TEST_MAPS[e % 3]`), the voxel world's
    task: the agent looks round at A (when the goal was seen), then walks out `--out-steps`
    steps with a turn of 15° either way after every second step, to B. The goal is A's view
    before the walk (seen: in memory) or A's view turned round (unseen: never observed).
    Acting renders the engine's frame at the new pose (a step into a wall stays put) and
    observes it with its depth; the planner's candidates are dead-reckoned poses (it does not
    know the walls) with their actions; the renderer draws any pose."""

    # A step, a step steered 10° either way, a turn in place of 15° either way (positive turns
    # right), as the Doom suites walk; and a step back, as the voxel world's planner has.
    MOVES = [{"forward": True}, {"forward": True, "yaw_deg": 10.0}, {"forward": True, "yaw_deg": -10.0},
             {"yaw_deg": 15.0}, {"yaw_deg": -15.0}, {"back": True}]
    unit = "m"

    def __init__(self, c: Client, a):
        self.moves = len(self.MOVES)
        self.actions = self.MOVES + ([STAY] if a.stop == "stay" else [])
        # Imported here: only a Doom run needs the Doom tool (the checkout's doom/, with vizdoom).
        sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "doom"))
        from worldpack_doom import engine, suite, walk
        self.E, self.S, self.W = engine, suite, walk
        self.c, self.a, self.engines, self.state = c, a, {}, {}

    def world(self, map_name: str):
        if map_name not in self.engines:
            engine = self.E.Engine(map_name, seed=0)
            self.engines[map_name] = (engine, self.W.Geometry(engine.sectors()))
        return self.engines[map_name]

    def frame(self, engine, x: float, y: float, angle: float):
        view = engine.view_at(x, y, angle)
        rgb, depth = self.S.to_frame(view)
        return rgb, depth, self.E.map_to_world(view.c2m())

    def walk_out(self, rng: np.random.Generator):
        """The walk's actions (indices into `actions`): steps, a turn after every second."""
        out = []
        for i in range(self.a.out_steps):
            out.append(0)
            if i % 2 == 1 and i + 1 < self.a.out_steps:
                out.append(int(rng.choice([3, 4])))
        return out

    def start(self, e: int, seen: bool, rng: np.random.Generator):
        map_name = self.S.TEST_MAPS[e % len(self.S.TEST_MAPS)]
        engine, geom = self.world(map_name)
        walk = self.walk_out(rng)
        # A start from which the whole walk is free, so that its way back can be walked exactly.
        for p, angle in self.W.start_points(engine.sectors(), geom, 40, rng):
            line, free = [(p, angle)], True
            for choice in walk:
                x, a_ = self.move(None, *line[-1], choice, walls=False)
                free = free and (np.allclose(x, line[-1][0]) or geom.free(line[-1][0], x))
                line.append((x, a_))
            if free:
                break
        else:
            raise SystemExit(f"{map_name}: no free walk of {self.a.out_steps} steps from 40 starting points")
        look = [(p, angle - self.W.TURN_STEP * (k + 1)) for k in range(int(360 / self.W.TURN_STEP))] if seen else []
        poses = [(p, angle)] + look + line[1:]
        rgb, depth, pose = self.frame(engine, *p, angle)
        s = self.c.create_session(frames=[(rgb, pose)], intrinsics=self.S.intrinsics())
        for (q, qa), (pq, pa) in zip(poses[1:], poses[:-1]):
            rgb, depth, pose = self.frame(engine, *q, qa)
            moved = not np.allclose(q, pq)
            yaw = (pa - qa + 180.0) % 360.0 - 180.0
            self.c.observe(s, rgb, pose, depth_mm=depth, action={"forward": bool(moved), "yaw_deg": float(yaw)})
        goal = (p, angle) if seen else (p, angle + 180.0)
        goal_image, _, _ = self.frame(engine, *goal[0], goal[1])
        x, a_ = line[-1]
        self.state[s] = (map_name, np.asarray(x, float), a_, self.eye(pose))
        return s, goal_image, goal, rgb, (x, a_)

    def move(self, geom, x: np.ndarray, angle: float, choice: int, walls: bool):
        act = self.actions[choice]
        angle = angle - act.get("yaw_deg", 0.0)
        if act.get("forward") or act.get("back"):
            q = x + (1.0 if act.get("forward") else -1.0) * self.W.WALK_STEP * self.W.heading_vector(angle)
            if not walls or geom.free(x, q):
                x = q
        return x, angle

    def act(self, s: int, choice: int):
        map_name, x, angle, _ = self.state[s]
        engine, geom = self.world(map_name)
        x, angle = self.move(geom, x, angle, choice, walls=True)
        rgb, depth, pose = self.frame(engine, *x, angle)
        self.c.observe(s, rgb, pose, depth_mm=depth, action=self.actions[choice])
        self.state[s] = (map_name, x, angle, self.eye(pose))
        return rgb, (x, angle)

    def imagine(self, s: int, seqs: np.ndarray, goal: np.ndarray):
        map_name, x0, a0, eye = self.state[s]
        poses = []
        for seq in seqs:
            x, angle, track = x0, a0, []
            for i in seq:
                x, angle = self.move(None, x, angle, int(i), walls=False)
                # At the present eye height: floors differ between sectors and maps, and a
                # candidate drawn a few metres above or below the floor sees nothing it should.
                track.append(self.E.map_to_world(self.E.camera_to_map(*x, eye, angle)))
            poses.append(track)
        return self.c.imagine(s, [[self.actions[i] for i in seq] for seq in seqs], poses=poses, seed=self.a.seed,
                              frames="none", goal=goal, goal_score=goal_scoring(self.a), steps=self.a.sampler_steps)

    def rendered(self, s: int, seqs: np.ndarray, goal: np.ndarray) -> np.ndarray:
        map_name, x0, a0, _ = self.state[s]
        engine, geom = self.world(map_name)
        out = []
        for seq in seqs:
            x, angle = x0, a0
            for i in seq:
                x, angle = self.move(geom, x, angle, int(i), walls=True)
            out.append(psnr(self.frame(engine, *x, angle)[0], goal))
        return np.array(out)

    def eye(self, pose: np.ndarray) -> float:
        """The eye's height in map units (the floor's plus the eye's) of a world pose."""
        return float(pose[1, 3] * self.E.UNITS_PER_METRE)

    def apart(self, a, b) -> tuple[float, float]:
        """Distance (metres) and heading difference (degrees) of two (map point, angle) poses."""
        (pa, aa), (pb, ab) = a, b
        return float(np.linalg.norm(np.asarray(pa) - np.asarray(pb)) / self.E.UNITS_PER_METRE), \
            abs((aa - ab + 180.0) % 360.0 - 180.0)

    def end(self, s: int) -> None:
        self.state.pop(s, None)
        self.c.delete_session(s)

    def close(self) -> None:
        for engine, _ in self.engines.values():
            engine.close()


def goal_scoring(a) -> str:
    """Scored in latent space, the server need not decode the last imagined step."""
    return "latent" if a.score == "latent" else "both"


def every_sequence(world, s: int, goal: np.ndarray, a) -> tuple[np.ndarray, float]:
    """The best of all n^H sequences (they share prefixes, so the server makes n + n² + ...
    frames, not H·n^H), and its score."""
    n = len(world.actions)
    seqs = np.array(np.meshgrid(*[np.arange(n)] * a.horizon, indexing="ij")).reshape(a.horizon, -1).T
    # The most staying first: a tie (a turn and its undoing against staying put) goes to staying.
    seqs = seqs[np.argsort(-(seqs >= world.moves).sum(axis=1), kind="stable")]
    scores = score(world, s, goal, seqs, a)
    best = int(np.argmax(scores))
    # A move may be asked to beat staying put throughout (the first sequence) by a margin, for
    # the imagination's error; 0 by default: on Doom's dev episodes 0.25-1 dB stopped it short.
    if a.stop == "stay" and scores[best] - scores[0] < a.stop_margin:
        best = 0
    return seqs[best], float(scores[best])


def cem(world, s: int, goal: np.ndarray, a, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """The best sequence the cross-entropy method finds (indices into the world's actions), and its score."""
    n = len(world.actions)
    probs = np.full((a.horizon, n), 1.0 / n)
    best, best_score = None, -np.inf
    for _ in range(a.iterations):
        seqs = np.array([[rng.choice(n, p=p) for p in probs] for _ in range(a.candidates)])
        scores = score(world, s, goal, seqs, a)
        order = np.argsort(-scores)
        if scores[order[0]] > best_score:
            best, best_score = seqs[order[0]], float(scores[order[0]])
        elites = seqs[order[: a.elites]]
        probs = np.stack([np.bincount(elites[:, h], minlength=n) + 0.5 for h in range(a.horizon)])
        probs /= probs.sum(axis=1, keepdims=True)
    return best, best_score


def score(world, s: int, goal: np.ndarray, seqs: np.ndarray, a) -> np.ndarray:
    """Each sequence's last frame against the goal, higher is closer: imagined by the
    served model, or (`--policy truth`) drawn by the world's renderer."""
    if a.policy == "truth":
        return world.rendered(s, seqs, goal)
    r = world.imagine(s, seqs, goal)
    if a.score == "latent":
        # In decibels, as PSNR is, so that one --stop-margin reads the same for both.
        return np.array([-10.0 * np.log10(max(ro.goal["latent_mse"], 1e-12)) for ro in r.rollouts])
    return np.array([ro.goal["psnr_db"] for ro in r.rollouts])


def run_episode(world, e: int, a) -> dict:
    rng = np.random.default_rng(a.first_world + e)
    seen = e % 2 == 0
    s, goal, goal_pose, view, start_pose = world.start(e, seen, rng)
    pose, steps, decide_s, stopped, visited = start_pose, 0, [], False, [start_pose]
    views = [view]
    while steps < a.max_steps:
        if a.stop == "view" and psnr(view, goal) >= a.stop_db:
            stopped = True
            break
        t = time.perf_counter()
        if a.policy == "random":
            choice = int(rng.integers(world.moves))
        else:
            best, _ = every_sequence(world, s, goal, a) if a.search == "all" else cem(world, s, goal, a, rng)
            # Staying first and moving after is the move now; staying throughout is the stop.
            moving = [int(i) for i in best if i < world.moves]
            choice = moving[0] if moving else None
        decide_s.append(time.perf_counter() - t)
        if choice is None:
            stopped = True
            break
        view, pose = world.act(s, choice)
        views.append(view)
        steps += 1
        # Back where it stood before (a move undone, a step into a wall): the planner is
        # circling a place its imagination cannot tell from the goal, so it stops there.
        if a.stop_on_return and any(d < 1e-3 and deg < 0.5 for d, deg in (world.apart(pose, v) for v in visited)):
            stopped = True
            break
        visited.append(pose)
    reach, turn = world.apart(pose, goal_pose)
    start_reach, start_turn = world.apart(start_pose, goal_pose)
    world.end(s)
    if a.pictures:
        write_strip(Path(a.pictures) / f"episode-{e:02d}.png", goal, views)
    return {"episode": e, "world": a.first_world + e, "goal_seen": seen, "stopped": stopped, "steps": steps,
            "success": bool(stopped and reach <= a.reach and turn <= a.turn), "final_distance": reach, "final_deg": turn,
            "start_distance": start_reach, "start_deg": start_turn, "final_psnr_db": psnr(view, goal),
            "decide_s_median": float(np.median(decide_s)) if decide_s else 0.0}


def write_strip(path: Path, goal: np.ndarray, views: list[np.ndarray]) -> None:
    """The goal, a gap, then the agent's view at the start and after every action, at 2x."""
    gap = np.full((goal.shape[0], goal.shape[1] // 4, 3), 255, np.uint8)
    strip = np.concatenate([goal, gap, *views], axis=1).repeat(2, axis=0).repeat(2, axis=1)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(png_bytes(strip))


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
                         f"final {np.mean([r['final_distance'] for r in sel]):.2f} away / {np.mean([r['final_deg'] for r in sel]):.0f}°")
    decided = [r["decide_s_median"] for r in rows if r["steps"] > 0 and r["decide_s_median"] > 0]
    if decided:
        lines[0] += f", decision {np.median(decided):.2f} s (median of the episodes' medians)"
    return "\n".join(lines)


def sign_test(won: int, lost: int) -> float:
    """Two-sided p of `won` against `lost` episodes under no difference (ties dropped)."""
    n = won + lost
    return min(1.0, 2 * sum(math.comb(n, i) for i in range(min(won, lost) + 1)) / 2 ** n) if n else 1.0


def compare(a_path: str, b_path: str) -> None:
    a, b = (json.loads(Path(p).read_text()) for p in (a_path, b_path))
    for run in (a, b):
        print(f"{run['label']}:\n" + "\n".join("  " + line for line in summary(run["episodes"]).splitlines()))
    by = {r["episode"]: r for r in b["episodes"]}
    pairs = [(r, by[r["episode"]]) for r in a["episodes"] if r["episode"] in by]
    print(f"{a['label']} − {b['label']}, paired over {len(pairs)} episodes (mean [95% interval]):")
    for what, key, sel in [("success", "success", None), ("steps", "steps", None), ("final distance", "final_distance", None),
                           ("final distance, seen", "final_distance", True), ("final distance, unseen", "final_distance", False)]:
        d = np.array([float(x[key]) - float(y[key]) for x, y in pairs if sel is None or x["goal_seen"] == sel])
        if len(d):
            m, lo, hi = bootstrap(d)
            print(f"  {what:<24} {m:+.2f} [{lo:+.2f}, {hi:+.2f}]")
    won = sum(x["success"] and not y["success"] for x, y in pairs)
    lost = sum(y["success"] and not x["success"] for x, y in pairs)
    print(f"  episodes won {won}, lost {lost} (sign test p = {sign_test(won, lost):.3f})")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", default="http://127.0.0.1:8080")
    ap.add_argument("--policy", choices=["model", "random", "truth"], default="model",
                    help="plan with the server's model, act at random, or plan with the world's renderer")
    ap.add_argument("--episodes", type=int, default=8)
    ap.add_argument("--world", choices=["voxel", "doom"], default="voxel",
                    help="the server's synthetic voxel world, or ViZDoom's held-out maps (serve a Doom model)")
    ap.add_argument("--first-world", type=int, default=100,
                    help="episode e draws its world (voxel: synthetic seed) or its start (Doom) from first-world + e")
    ap.add_argument("--out-steps", type=int, default=None,
                    help="steps walked out before the agent plans its way to the goal (voxel 6, Doom 6)")
    ap.add_argument("--max-steps", type=int, default=20)
    ap.add_argument("--search", choices=["cem", "all"], default=None,
                    help="the cross-entropy method over --candidates sequences (voxel), or every sequence of the horizon (Doom)")
    ap.add_argument("--candidates", type=int, default=6)
    ap.add_argument("--horizon", type=int, default=2)
    ap.add_argument("--iterations", type=int, default=2)
    ap.add_argument("--elites", type=int, default=3)
    ap.add_argument("--score", choices=["psnr", "latent"], default=None,
                    help="the imagined last frame against the goal (voxel psnr; Doom latent, which leaves it undecoded)")
    ap.add_argument("--sampler-steps", type=int, default=None)
    ap.add_argument("--stop", choices=["view", "stay"], default=None,
                    help="stop when the view is within --stop-db of the goal (voxel), or when the planner's best future is to stay put (Doom; random moves then stop only by --stop-on-return)")
    ap.add_argument("--stop-margin", type=float, default=None,
                    help="with --stop stay, a move is taken only if its best future scores this many dB over staying put")
    ap.add_argument("--stop-on-return", type=int, choices=[0, 1], default=None,
                    help="1: also stop on coming back to a pose already stood at in the episode (Doom 1, voxel 0)")
    ap.add_argument("--stop-db", type=float, default=None,
                    help="stop when the view's PSNR against the goal reaches this (voxel 22, Doom 30: a Doom view a step from the goal's scores 24 to 34)")
    ap.add_argument("--reach", type=float, default=None,
                    help="success: within this distance of the goal's position (voxel 0.5 blocks, Doom 0.5 m)")
    ap.add_argument("--turn", type=float, default=20.0, help="and this many degrees of its heading")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", default=None, help="run only these episodes (comma-separated numbers)")
    ap.add_argument("--pictures", default=None, help="write each episode's goal and views as a PNG strip into this folder")
    ap.add_argument("--label", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"))
    a = ap.parse_args()
    if a.compare:
        compare(*a.compare)
        return
    for key, value in DEFAULTS[a.world].items():
        if getattr(a, key) is None:
            setattr(a, key, value)
    world = (DoomWorld if a.world == "doom" else VoxelWorld)(Client(a.url), a)
    label = a.label or f"{a.policy} @ {a.url}"
    rows = []
    try:
        for e in ([int(x) for x in a.only.split(",")] if a.only else range(a.episodes)):
            r = run_episode(world, e, a)
            rows.append(r)
            print(f"episode {e:2d} goal {'seen' if r['goal_seen'] else 'unseen':<6} {'success' if r['success'] else 'miss   '} "
                  f"in {r['steps']:2d} steps; {r['start_distance']:.2f} → {r['final_distance']:.2f} {world.unit}, "
                  f"{r['start_deg']:.0f} → {r['final_deg']:.0f}°, decision {r['decide_s_median']:.2f} s", flush=True)
    finally:
        world.close()
    print(summary(rows))
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps({"label": label, "settings": {k: v for k, v in vars(a).items() if k not in ("compare", "out")},
                                           "episodes": rows}, indent=1))
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
