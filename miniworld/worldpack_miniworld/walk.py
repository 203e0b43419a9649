"""LoopNav-style walks in a MiniWorld environment, planned on its floor plan
with the project's kinematic motion model, so every frame's action is exact.

Every walk looks around at A first (24 turns of 15 degrees). ABA walks to a
B about `range` metres from A, turns round and comes back through the same
points in reverse, so the way back revisits what the way out saw. ABCA walks
to B, on to a C about a range from both, and back to A by a way that keeps
off the way out where the floor plan has one.

Each step is what `motion::Kinematic` does with an action: turn by `yaw_deg`
(positive turns right), then move WALK_STEP along the new heading when
`forward`. Legs follow shortest paths on a 0.2 m grid of the floor that keeps
PLAN_CLEARANCE from every wall and object (and prefers more), by pure
pursuit: a step may turn at most MAX_STEER; facing more than TURN_IN_PLACE
away from the path it turns in place, 15 degrees a frame. No step comes
closer than CLEARANCE to a wall or an object."""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np

from .engine import heading_vector

WALK_STEP = 0.216         # motion::WALK_SPEED, metres a step
TURN_STEP = 15.0          # degrees a frame when turning in place (look-around, turn-round)
MAX_STEER = 10.0          # degrees a walking step may turn
TURN_IN_PLACE = 45.0      # facing further than this from the path, turn in place first
CLEARANCE = 0.4           # metres every camera position keeps from walls and objects (MiniWorld's agent radius)
PLAN_CLEARANCE = 0.6      # metres the planned paths keep
START_CLEARANCE = 0.9     # metres around A (room for the look-around)
CELL = 0.2                # grid cell (m)
LOOKAHEAD = 0.6           # metres of path ahead that pure pursuit steers at
MAX_FRAMES = 300          # a longer walk is drawn again
MAX_DETOUR = 2.0          # a leg's path is at most this many ranges long
TRIES = 8                 # starting points tried in one world
LOOK_AROUND = int(360 / TURN_STEP)
TURN_ROUND = int(180 / TURN_STEP)


def _wrap(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


def _heading_to(p: np.ndarray, q: np.ndarray) -> float:
    d = q - p
    return float(np.degrees(np.arctan2(-d[1], d[0])))


class FloorPlan:
    """What a walker can stand on in a loaded MiniWorld world: inside a room
    (MiniWorld's rooms are convex; doorways are rooms of their own), away from
    the walls that reach the floor and from every object's bounding circle.
    Points are floor-plane (x, z) in metres."""

    def __init__(self, env):
        self.segs = np.asarray(env.wall_segs, float)[:, :, [0, 2]].reshape(-1, 4)
        self.rooms = [(np.asarray(r.outline, float)[:, [0, 2]], np.asarray(r.edge_norms, float)[:, [0, 2]]) for r in env.rooms]
        self.objects = np.array([[e.pos[0], e.pos[2], float(e.radius)] for e in env.entities
                                 if e is not env.agent and float(e.radius) > 0], float).reshape(-1, 3)
        self.lo = np.array([env.min_x, env.min_z], float)
        self.hi = np.array([env.max_x, env.max_z], float)
        shape = np.ceil((self.hi - self.lo) / CELL).astype(int)
        self.shape = (int(shape[0]), int(shape[1]))
        gx, gz = np.meshgrid(np.arange(self.shape[0]), np.arange(self.shape[1]), indexing="ij")
        self.centres = self.lo + (np.stack([gx, gz], -1) + 0.5) * CELL
        flat = self.centres.reshape(-1, 2)
        room = np.zeros(len(flat), bool)
        for outline, norms in self.rooms:
            room |= np.all(((flat[:, None, :] - outline[None]) * norms[None]).sum(-1) > 0, axis=1)
        self.clear = np.where(room, self.clearance(flat), 0.0).reshape(self.shape)

    def clearance(self, p: np.ndarray) -> np.ndarray:
        """Distance from each point (..., 2) to the nearest wall or object edge."""
        p = np.asarray(p, float)
        flat = p.reshape(-1, 2)
        out = np.full(len(flat), np.inf)
        a, b = self.segs[:, :2], self.segs[:, 2:]
        ab = b - a
        den = np.maximum((ab * ab).sum(1), 1e-12)
        for i in range(0, len(flat), 4096):
            q = flat[i:i + 4096, None, :]
            t = np.clip(((q - a) * ab).sum(-1) / den, 0.0, 1.0)
            d = np.sqrt((((a + t[..., None] * ab) - q) ** 2).sum(-1)).min(1) if len(ab) else np.full(len(q), np.inf)
            if len(self.objects):
                d = np.minimum(d, (np.sqrt(((q - self.objects[None, :, :2]) ** 2).sum(-1)) - self.objects[None, :, 2]).min(1))
            out[i:i + 4096] = d
        return out.reshape(p.shape[:-1])

    def inside(self, p: np.ndarray) -> bool:
        return any(np.all(((p - outline) * norms).sum(1) > 0) for outline, norms in self.rooms)

    def crosses(self, p: np.ndarray, q: np.ndarray) -> bool:
        a, b = self.segs[:, :2], self.segs[:, 2:]
        d, s = q - p, b - a
        den = d[0] * s[:, 1] - d[1] * s[:, 0]
        w = a - p
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (w[:, 0] * s[:, 1] - w[:, 1] * s[:, 0]) / den
            u = (w[:, 0] * d[1] - w[:, 1] * d[0]) / den
        return bool(np.any((t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)))

    def free(self, p: np.ndarray, q: np.ndarray) -> bool:
        """A step from p to q: no wall crossed, q inside and CLEARANCE from everything."""
        return not self.crosses(p, q) and self.inside(q) and float(self.clearance(q)) >= CLEARANCE

    def cell(self, p: np.ndarray) -> tuple[int, int]:
        i = np.clip(((np.asarray(p) - self.lo) / CELL).astype(int), 0, np.array(self.shape) - 1)
        return int(i[0]), int(i[1])

    def walkable(self) -> np.ndarray:
        return self.clear >= PLAN_CLEARANCE

    def distances(self, source: tuple[int, int], avoid: np.ndarray | None = None):
        """Shortest-path lengths (m) over walkable cells from `source`, 8-connected,
        each step's length raised where the clearance is below 1 m (paths keep
        to the middle of doorways and corridors) and tenfold on `avoid` cells;
        with the predecessor of each cell."""
        walk = self.walkable()
        weight = 1.0 + 2.0 * np.clip(1.0 - self.clear, 0.0, None)
        if avoid is not None:
            weight = weight * np.where(avoid, 10.0, 1.0)
        nx, nz = self.shape
        dist = np.full(self.shape, np.inf)
        prev = np.full(self.shape + (2,), -1, np.int32)
        dist[source] = 0.0
        heap = [(0.0, source)]
        steps = [(dx, dz, CELL * np.hypot(dx, dz)) for dx in (-1, 0, 1) for dz in (-1, 0, 1) if dx or dz]
        while heap:
            d, (i, j) = heapq.heappop(heap)
            if d > dist[i, j]:
                continue
            for dx, dz, length in steps:
                a, b = i + dx, j + dz
                if 0 <= a < nx and 0 <= b < nz and walk[a, b]:
                    if dx and dz and not (walk[i + dx, j] and walk[i, j + dz]):
                        continue
                    nd = d + length * 0.5 * (weight[i, j] + weight[a, b])
                    if nd < dist[a, b]:
                        dist[a, b] = nd
                        prev[a, b] = (i, j)
                        heapq.heappush(heap, (nd, (a, b)))
        return dist, prev

    def path(self, prev: np.ndarray, source: np.ndarray, target: np.ndarray) -> np.ndarray:
        """The points from `source` to `target` through the predecessors of a `distances` run from source."""
        c = self.cell(target)
        cells = [c]
        while prev[c][0] >= 0:
            c = (int(prev[c][0]), int(prev[c][1]))
            cells.append(c)
        pts = [self.centres[i, j] for i, j in reversed(cells)]
        return np.array([source, *pts[1:-1], target], float)

    def path_length(self, points: np.ndarray) -> float:
        return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


@dataclass
class Plan:
    """Floor points (x, z) and headings (degrees; see engine) of every frame,
    the action that led to each, and each frame's phase (0 look-around,
    1 outbound, 2 way back)."""
    points: list = field(default_factory=list)
    headings: list = field(default_factory=list)
    forward: list = field(default_factory=list)
    yaw: list = field(default_factory=list)      # motion's sense: positive turns right
    phase: list = field(default_factory=list)

    def add(self, point, heading, forward, yaw, phase):
        self.points.append(np.asarray(point, float))
        self.headings.append(_wrap(float(heading)))
        self.forward.append(bool(forward))
        self.yaw.append(float(yaw))
        self.phase.append(phase)

    def step(self, yaw: float, forward: bool, phase: int) -> None:
        heading = self.headings[-1] - yaw
        point = self.points[-1] + (WALK_STEP * heading_vector(heading) if forward else 0.0)
        self.add(point, heading, forward, yaw, phase)

    @property
    def returning_point(self) -> int:
        return self.phase.index(2)

    def __len__(self) -> int:
        return len(self.points)


def look_around(start: np.ndarray, heading: float) -> Plan:
    """The start of every walk: a full turn to the right in place at A."""
    plan = Plan()
    plan.add(start, heading, False, 0.0, 0)
    for _ in range(LOOK_AROUND):
        plan.step(TURN_STEP, False, 0)
    return plan


def follow(plan: Plan, floor: FloorPlan, path: np.ndarray, phase: int, max_steps: int = 400) -> bool:
    """Walks `plan` along `path` (which starts where the plan stands) by pure
    pursuit, ending within a step of its end; False when a step would not be free."""
    goal = path[-1]
    a, ab = path[:-1], np.diff(path, axis=0)
    seg_len = np.linalg.norm(ab, axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg_len)])
    progress = 0.0
    for _ in range(max_steps):
        p, h = plan.points[-1], plan.headings[-1]
        if np.linalg.norm(goal - p) < 0.6 * WALK_STEP:
            return True
        # Progress along the path: its nearest point to p, searched a little behind and ahead of the last.
        t = np.clip(((p - a) * ab).sum(1) / np.maximum(seg_len**2, 1e-12), 0.0, 1.0)
        at = arc[:-1] + t * seg_len
        d = np.linalg.norm(a + t[:, None] * ab - p, axis=1)
        d[(at < progress - 0.3) | (at > progress + 1.0)] = np.inf
        progress = max(progress, float(at[np.argmin(d)]))
        s = min(progress + LOOKAHEAD, arc[-1])
        k = int(np.clip(np.searchsorted(arc, s, side="right") - 1, 0, len(ab) - 1))
        target = goal if np.linalg.norm(goal - p) < LOOKAHEAD else a[k] + (s - arc[k]) / max(seg_len[k], 1e-12) * ab[k]
        off = _wrap(h - _heading_to(p, target))   # positive: the target is to the right
        if abs(off) > TURN_IN_PLACE:
            plan.step(float(np.clip(off, -TURN_STEP, TURN_STEP)), False, phase)
            continue
        yaw = float(np.clip(off, -MAX_STEER, MAX_STEER))
        q = p + WALK_STEP * heading_vector(h - yaw)
        if not floor.free(p, q):
            return False
        plan.step(yaw, True, phase)
    return False


def _draw(rng: np.random.Generator, floor: FloorPlan, mask: np.ndarray) -> np.ndarray | None:
    cells = np.argwhere(mask)
    if len(cells) == 0:
        return None
    i, j = cells[rng.integers(len(cells))]
    return floor.centres[i, j] + rng.uniform(-0.5, 0.5, 2) * CELL


def _ring(floor: FloorPlan, centre: np.ndarray, range_m: float, dist: np.ndarray) -> np.ndarray:
    """Walkable cells 0.8 to 1.2 ranges from `centre` as the crow flies and
    at most MAX_DETOUR ranges away on foot (path lengths as `distances` weighs them)."""
    r = np.linalg.norm(floor.centres - centre, axis=-1)
    return floor.walkable() & (r >= 0.8 * range_m) & (r <= 1.2 * range_m) & (dist <= MAX_DETOUR * range_m)


def out_and_back(floor: FloorPlan, range_m: float, rng: np.random.Generator) -> Plan | None:
    """One ABA walk, or None when this draw found no B or would run too long."""
    start = _draw(rng, floor, floor.clear >= START_CLEARANCE)
    if start is None:
        return None
    dist, prev = floor.distances(floor.cell(start))
    b = _draw(rng, floor, _ring(floor, start, range_m, dist))
    if b is None:
        return None
    plan = look_around(start, rng.uniform(-180.0, 180.0))
    first_out = len(plan)
    if not follow(plan, floor, floor.path(prev, start, b), 1):
        return None
    out = len(plan)
    for _ in range(TURN_ROUND):                 # turn round at B
        plan.step(TURN_STEP, False, 1)
    # Retrace: the k-th outbound step turned by yaw_k then moved; going back,
    # step j turns by -yaw of the step after the one it undoes, then moves.
    steps = list(zip(plan.yaw[first_out:out], plan.forward[first_out:out]))
    previous_yaw = 0.0
    for yaw, fwd in reversed(steps):
        plan.step(-previous_yaw, fwd, 2)
        previous_yaw = yaw
    return plan if len(plan) <= MAX_FRAMES else None


def loop_back(floor: FloorPlan, range_m: float, rng: np.random.Generator) -> Plan | None:
    """One ABCA walk: A, B and C about a range apart; the way back is the walk
    from C to A, kept off the way out where it can be. None when no such B
    and C were found, the walk would run too long, or the way back's middle
    comes within a metre of the way out."""
    start = _draw(rng, floor, floor.clear >= START_CLEARANCE)
    if start is None:
        return None
    dist_a, prev_a = floor.distances(floor.cell(start))
    b = _draw(rng, floor, _ring(floor, start, range_m, dist_a))
    if b is None:
        return None
    dist_b, _ = floor.distances(floor.cell(b))
    c = _draw(rng, floor, _ring(floor, start, range_m, dist_a) & _ring(floor, b, range_m, dist_b))
    if c is None:
        return None
    plan = look_around(start, rng.uniform(-180.0, 180.0))
    if not follow(plan, floor, floor.path(prev_a, start, b), 1):
        return None
    _, prev_c = floor.distances(floor.cell(c))   # B to C: the path from C, reversed
    if not follow(plan, floor, floor.path(prev_c, c, plan.points[-1])[::-1], 1):
        return None
    walked = np.array(plan.points)
    near = np.zeros(floor.shape, bool)
    for p in walked[::2]:
        near |= np.linalg.norm(floor.centres - p, axis=-1) < 1.2
    _, prev_back = floor.distances(floor.cell(start), avoid=near)
    back = floor.path(prev_back, start, plan.points[-1])[::-1]
    if not follow(plan, floor, back, 2) or np.linalg.norm(plan.points[-1] - start) > 0.5:
        return None
    way_back = np.array(plan.points[plan.returning_point:])
    if np.linalg.norm(walked - way_back[len(way_back) // 2], axis=1).min() < 1.0:
        return None
    return plan if len(plan) <= MAX_FRAMES else None


def _tries(task):
    def draw(floor: FloorPlan, range_m: float, rng: np.random.Generator, tries: int = TRIES) -> Plan | None:
        for _ in range(tries):
            plan = task(floor, range_m, rng)
            if plan is not None:
                return plan
        return None
    draw.__doc__ = f"{task.__doc__} Up to `tries` starting points."
    return draw


TASKS = {"aba": _tries(out_and_back), "abca": _tries(loop_back)}
