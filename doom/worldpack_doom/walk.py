"""LoopNav-style walks on a Doom map, planned on the map's geometry with the
project's kinematic motion model, so every frame's action is exact. Both
tasks look around at A first. ABA walks to a B at least 0.8 range away,
turns round and comes back along the same points in reverse; ABCA walks to
B, on to a C a range from both, and back to A by a way it has not walked,
so the way back sees A's surroundings from new places.

Each step is what `motion::Kinematic` does with an action: turn by `yaw_deg`
(positive turns right), then move WALK_STEP along the new heading when
`forward`. The return leg retraces the outbound points, so the way back
revisits what the exploration saw, as LoopNav's ABA task does."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .engine import UNITS_PER_METRE

# motion::WALK_SPEED (0.216 m a step) in map units.
WALK_STEP = 0.216 * UNITS_PER_METRE
TURN_STEP = 15.0          # degrees a frame when turning in place (look-around, turn-round)
MAX_STEER = 10.0          # degrees a walking step may turn
CLEARANCE = 24.0          # map units kept from every wall (the player's radius is 16)
MAX_STEP_UP = 24.0        # Doom's step height
PLAYER_HEIGHT = 56.0


class Geometry:
    """The walls a walker cannot pass: one-sided and blocking lines, and
    two-sided lines whose floors differ by more than a step or whose opening
    is lower than the player."""

    def __init__(self, sectors):
        sides: dict[tuple, list] = {}
        blocking = set()
        for s in sectors:
            for line in s.lines:
                key = tuple(sorted([(line.x1, line.y1), (line.x2, line.y2)]))
                sides.setdefault(key, []).append(s)
                if line.is_blocking:
                    blocking.add(key)
        walls = []
        for key, ss in sides.items():
            wall = key in blocking or len(ss) < 2
            if not wall:
                a, b = ss[0], ss[1]
                opening = min(a.ceiling_height, b.ceiling_height) - max(a.floor_height, b.floor_height)
                wall = abs(a.floor_height - b.floor_height) > MAX_STEP_UP or opening < PLAYER_HEIGHT
            if wall:
                walls.append([*key[0], *key[1]])
        self.walls = np.array(walls, float).reshape(-1, 4)

    def clearance(self, p: np.ndarray) -> float:
        a, b = self.walls[:, :2], self.walls[:, 2:]
        ab = b - a
        t = np.clip(((p - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-9), 0.0, 1.0)
        return float(np.sqrt((((a + t[:, None] * ab) - p) ** 2).sum(1)).min())

    def crosses(self, p: np.ndarray, q: np.ndarray) -> bool:
        a, b = self.walls[:, :2], self.walls[:, 2:]
        d, s = q - p, b - a
        den = d[0] * s[:, 1] - d[1] * s[:, 0]
        w = a - p
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (w[:, 0] * s[:, 1] - w[:, 1] * s[:, 0]) / den
            u = (w[:, 0] * d[1] - w[:, 1] * d[0]) / den
        return bool(np.any((t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)))

    def free(self, p: np.ndarray, q: np.ndarray) -> bool:
        return not self.crosses(p, q) and self.clearance(q) >= CLEARANCE


def heading_vector(angle_deg: float) -> np.ndarray:
    a = np.radians(angle_deg)
    return np.array([np.cos(a), np.sin(a)])


@dataclass
class Plan:
    """Map points and angles (degrees counter-clockwise from +x) of every frame,
    the action that led to each, and each frame's phase (0 look-around,
    1 outbound, 2 way back)."""
    points: list = field(default_factory=list)
    angles: list = field(default_factory=list)
    forward: list = field(default_factory=list)
    yaw: list = field(default_factory=list)      # motion's sense: positive turns right
    phase: list = field(default_factory=list)

    def add(self, point, angle, forward, yaw, phase):
        self.points.append(np.asarray(point, float))
        self.angles.append(float(angle) % 360.0)
        self.forward.append(bool(forward))
        self.yaw.append(float(yaw))
        self.phase.append(phase)

    def step(self, yaw: float, forward: bool, phase: int) -> None:
        angle = self.angles[-1] - yaw
        point = self.points[-1] + (WALK_STEP * heading_vector(angle) if forward else 0.0)
        self.add(point, angle, forward, yaw, phase)

    @property
    def returning_point(self) -> int:
        return self.phase.index(2)


def wander(geom: Geometry, start: np.ndarray, angle: float, steps: int, rng: np.random.Generator,
           goal: np.ndarray | None = None) -> list[tuple[float, bool]]:
    """Actions (yaw, forward) of a walker that drifts (or heads for `goal`)
    and turns away from walls; stops early at the goal."""
    p, a, steer, out = start.copy(), angle, 0.0, []
    for _ in range(steps):
        if goal is not None:
            if np.linalg.norm(goal - p) < 2 * WALK_STEP:
                break
            want = np.degrees(np.arctan2(*(goal - p)[::-1]))
            steer = 0.5 * steer + 0.5 * ((a - want + 180.0) % 360.0 - 180.0) + rng.normal(0.0, 3.0)
        else:
            steer = 0.85 * steer + rng.normal(0.0, 3.0)
        yaw = float(np.clip(steer, -MAX_STEER, MAX_STEER))
        q = p + WALK_STEP * heading_vector(a - yaw)
        if geom.free(p, q):
            out.append((yaw, True))
            a, p = a - yaw, q
            continue
        # Blocked: turn in place towards the side with more room.
        room = [geom.clearance(p + 4 * WALK_STEP * heading_vector(a - s * 45.0)) for s in (1, -1)]
        yaw = TURN_STEP if room[0] >= room[1] else -TURN_STEP
        out.append((yaw, False))
        a -= yaw
        steer = 0.0
    return out


def look_around(start: np.ndarray, start_angle: float) -> Plan:
    """The start of every walk: a full turn in place at A."""
    plan = Plan()
    plan.add(start, start_angle, False, 0.0, 0)
    for _ in range(int(360 / TURN_STEP)):
        plan.step(TURN_STEP, False, 0)
    return plan


def out_and_back(geom: Geometry, start: np.ndarray, start_angle: float, range_units: float,
                 rng: np.random.Generator, max_steps: int = 240) -> Plan | None:
    """One ABA walk from `start`, or None when no B at least 0.8 range away was reached."""
    plan = look_around(start, start_angle)
    direction = rng.uniform(0.0, 360.0)
    goal = start + range_units * heading_vector(direction)
    for yaw, fwd in wander(geom, start, plan.angles[-1], max_steps, rng, goal):
        plan.step(yaw, fwd, 1)
    b = plan.points[-1]
    if np.linalg.norm(b - start) < 0.8 * range_units:
        return None
    out = len(plan.points)
    first_out = int(360 / TURN_STEP) + 1
    for _ in range(int(180 / TURN_STEP)):                 # turn round at B
        plan.step(TURN_STEP, False, 1)
    # Retrace: the k-th outbound step turned by yaw_k then moved; going back,
    # step j turns by -yaw of the step after the one it undoes, then moves.
    steps = list(zip(plan.yaw[first_out:out], plan.forward[first_out:out]))
    previous_yaw = 0.0
    for yaw, fwd in reversed(steps):
        plan.step(-previous_yaw, fwd, 2)
        previous_yaw = yaw
    return plan


def loop_back(geom: Geometry, start: np.ndarray, start_angle: float, range_units: float,
              rng: np.random.Generator, max_steps: int = 240) -> Plan | None:
    """One ABCA walk from `start`: A, B and C the corners of a triangle with
    sides of `range_units`; the way back is the walk from C to A. None when
    B or C was not reached or the walk ended more than a metre from A."""
    plan = look_around(start, start_angle)
    direction = rng.uniform(0.0, 360.0)
    corners = [start + range_units * heading_vector(direction + s) for s in (0.0, rng.choice([-60.0, 60.0]))]
    for goal in corners:
        for yaw, fwd in wander(geom, plan.points[-1], plan.angles[-1], max_steps, rng, goal):
            plan.step(yaw, fwd, 1)
        if np.linalg.norm(plan.points[-1] - goal) > 0.2 * range_units:
            return None
    for yaw, fwd in wander(geom, plan.points[-1], plan.angles[-1], max_steps, rng, start):
        plan.step(yaw, fwd, 2)
    if 2 not in plan.phase or np.linalg.norm(plan.points[-1] - start) > UNITS_PER_METRE:
        return None
    return plan


TASKS = {"aba": out_and_back, "abca": loop_back}


def start_points(sectors, geom: Geometry, count: int, rng: np.random.Generator,
                 min_clearance: float = 64.0, tries: int = 20000) -> list[tuple[np.ndarray, float]]:
    """Random starting points inside the map's sectors (a point inside a
    sector's boundary an odd number of times), where a player fits and the
    walls are at least `min_clearance` away; each with a random angle."""
    entries = [(i, line.x1, line.y1, line.x2, line.y2) for i, s in enumerate(sectors) for line in s.lines]
    owner = np.array([e[0] for e in entries])
    seg = np.array([e[1:] for e in entries], float)
    opening = np.array([s.ceiling_height - s.floor_height for s in sectors], float)
    lo, hi = geom.walls[:, :2].min(0), geom.walls[:, :2].max(0)
    points = []
    for _ in range(tries):
        p = rng.uniform(lo, hi)
        (x1, y1, x2, y2) = seg.T
        spans = (y1 > p[1]) != (y2 > p[1])
        with np.errstate(divide="ignore", invalid="ignore"):
            x_at = x1 + (p[1] - y1) * (x2 - x1) / (y2 - y1)
        crossings = np.bincount(owner[spans & (p[0] < x_at)], minlength=len(sectors))
        inside = np.flatnonzero(crossings % 2 == 1)
        if len(inside) != 1 or opening[inside[0]] < PLAYER_HEIGHT or geom.clearance(p) < min_clearance:
            continue
        points.append((p, float(rng.uniform(0.0, 360.0))))
        if len(points) == count:
            break
    return points
