"""The example planner's decision rule (clients/python/examples/plan_to_goal.py) on a world
of one line, where the score is known: it walks to the goal and stops there, a tie between
staying put and a move undone going to staying. The example against real servers is in
tests/test_python_client.py and tests/test_doom.py."""

import argparse
import importlib.util
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("plan_to_goal", ROOT / "clients" / "python" / "examples" / "plan_to_goal.py")
plan = importlib.util.module_from_spec(spec)
spec.loader.exec_module(plan)


class Line:
    """Positions 0, 1, 2, ... on a line; the goal at `goal`. A candidate's score is minus its
    end's distance from the goal, as a renderer would score it."""

    moves = 2
    actions = [{"forward": True}, {"back": True}, plan.STAY]
    unit = "steps"

    def __init__(self, goal: int):
        self.goal, self.x = goal, 0

    def view(self) -> np.ndarray:
        return np.full((4, 4, 3), 10 * self.x, np.uint8)

    def start(self, e, seen, rng):
        return 1, np.full((4, 4, 3), 10 * self.goal, np.uint8), self.goal, self.view(), 0

    def rendered(self, s, seqs, goal):
        step = {0: 1, 1: -1, 2: 0}
        return np.array([-abs(self.x + sum(step[int(i)] for i in seq) - self.goal) for seq in seqs], float)

    def act(self, s, choice):
        self.x += {0: 1, 1: -1}[choice]
        return self.view(), self.x

    def apart(self, a, b):
        return float(abs(a - b)), 0.0

    def end(self, s):
        pass


def settings(**kw):
    a = dict(policy="truth", search="all", horizon=2, stop="stay", stop_db=30.0, stop_margin=0.0, stop_on_return=0, pictures=None, max_steps=10, first_world=0, reach=0.5, turn=20.0)
    a.update(kw)
    return argparse.Namespace(**a)


def test_the_planner_walks_to_the_goal_and_stops_there():
    r = plan.run_episode(Line(goal=3), 0, settings())
    assert (r["steps"], r["stopped"], r["success"], r["final_distance"]) == (3, True, True, 0.0), r


def test_at_the_goal_staying_wins_the_tie_with_a_move_undone():
    # Forward then back ends where staying does, with the same score: the planner must stop.
    r = plan.run_episode(Line(goal=0), 0, settings())
    assert (r["steps"], r["stopped"], r["success"]) == (0, True, True), r


def test_without_the_stay_rule_a_planner_stops_by_the_view():
    world = Line(goal=2)
    world.actions = world.actions[:2]
    r = plan.run_episode(world, 0, settings(stop="view", stop_db=60.0))
    assert (r["steps"], r["stopped"], r["success"]) == (2, True, True), r


def test_a_stop_margin_keeps_moves_that_gain_less_than_it():
    # Two steps forward gain 2 over staying, one step 1: with a margin of 1.5 the planner
    # walks while the goal is two steps off and stops one step short of it.
    r = plan.run_episode(Line(goal=3), 0, settings(stop_margin=1.5))
    assert (r["steps"], r["stopped"], r["success"], r["final_distance"]) == (2, True, False, 1.0), r


class Dithering(Line):
    """A model that always favours the other way: forward from even places, back from odd."""

    def rendered(self, s, seqs, goal):
        favoured = self.x % 2
        return np.array([1.0 if int(seq[0]) == favoured else 0.0 for seq in seqs])


def test_coming_back_to_a_pose_it_stood_at_stops_the_planner_there():
    r = plan.run_episode(Dithering(goal=0), 0, settings(stop_on_return=1))
    assert (r["steps"], r["stopped"], r["final_distance"]) == (2, True, 0.0), r
    r = plan.run_episode(Dithering(goal=0), 0, settings())
    assert (r["steps"], r["stopped"]) == (10, False), r


def test_the_sign_test_counts_episodes_won_and_lost():
    # 3 won, none lost: 2 · (1/2)³; 6 to 1: 2 · (1 + 7)/2⁷.
    assert plan.sign_test(3, 0) == 0.25 and plan.sign_test(6, 1) == 0.125 and plan.sign_test(0, 0) == 1.0


def test_an_episode_is_drawn_as_the_goal_then_every_view(tmp_path):
    from worldpack_client.client import decode_image

    plan.run_episode(Line(goal=3), 0, settings(pictures=str(tmp_path)))
    strip = decode_image((tmp_path / "episode-00.png").read_bytes())
    # 4-pixel views at 2x: the goal, a 1-pixel gap, the start and the 3 views after each step.
    assert strip.shape == (8, 2 * (4 + 1 + 4 * 4), 3)
    assert (strip[:, :8] == 30).all() and (strip[:, 10:18] == 0).all() and (strip[:, -8:] == 30).all()
