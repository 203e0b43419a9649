"""How `worldpack train` divides `--hours` (train/worldpack_train/budget.py): the work that
grows with the dataset is set aside before the training stages share the rest, a stage that
ran long is paid for by the ones after it, and the held-out split and the head's walks stay
within their caps. Pure Python: no torch, no training."""

import pytest

from worldpack_train import budget
from worldpack_train import settings as wsettings


def walks(n, frames=200):
    return [{"dir": f"w{i:03d}", "frames": frames} for i in range(n)]


def fresh(**over):
    return wsettings.merge(wsettings.DEFAULTS, {"hours": 1.25, **over})


def test_a_large_dataset_sets_its_fixed_work_aside_and_the_budget_adds_up():
    s, stages = fresh(), {}
    small = budget.work_ahead(s, stages, walks(50), walks(5))
    large = budget.work_ahead(s, stages, walks(400), walks(24))
    assert large["latent cache"] > 7 * small["latent cache"]
    # The head's data and the eval stop growing at their caps.
    assert large["head data"] == pytest.approx(small["head data"] * 96 / 50)
    pool = budget.training_pool(s, stages, large)
    assert pool + sum(large.values()) == pytest.approx(75.0)
    minutes = {n: budget.training_minutes(s, stages, large, n) for n in budget.TRAINING_STAGES}
    assert sum(minutes.values()) == pytest.approx(pool)
    assert minutes["adversarial"] == 0.0  # a CPU run skips it
    assert minutes["teacher"] > minutes["baseline"] > minutes["autoencoder"] > 0


def test_a_stage_that_ran_long_is_paid_for_by_the_stages_after_it():
    s = fresh()
    train, held = walks(100), walks(10)
    before = {"split": {"status": "done", "minutes": 0.5}, "from": {"status": "done", "minutes": 0.2}}
    on_time = dict(before, autoencoder={"status": "done", "minutes": 5.0})
    late = dict(before, autoencoder={"status": "done", "minutes": 15.0})
    t_on = budget.training_minutes(s, on_time, budget.work_ahead(s, on_time, train, held), "teacher")
    t_late = budget.training_minutes(s, late, budget.work_ahead(s, late, train, held), "teacher")
    assert t_on - t_late == pytest.approx(10.0 * 0.38 / (0.22 + 0.38 + 0.30))
    # Spent past the budget: nothing is left to train, never a negative share.
    over = dict(before, autoencoder={"status": "done", "minutes": 200.0})
    assert budget.training_minutes(s, over, budget.work_ahead(s, over, train, held), "teacher") == 0.0


def test_a_gpu_run_gives_the_adversarial_student_part_of_the_students_share():
    s = fresh(device="cuda")
    ahead = budget.work_ahead(s, {}, walks(50), walks(5))
    adv = budget.training_minutes(s, {}, ahead, "adversarial")
    student = budget.training_minutes(s, {}, ahead, "student")
    assert adv > 0 and adv / student == pytest.approx(0.12 / 0.18)


def test_the_heldout_split_keeps_its_share_within_its_bounds():
    held = wsettings.DEFAULTS["heldout"]
    assert len(budget.heldout_picks(400, held)) == 24  # a tenth would be 40
    assert len(budget.heldout_picks(60, held)) == 6
    assert len(budget.heldout_picks(4, held)) == 1
    picks = sorted(budget.heldout_picks(400, held))
    assert picks[0] < 17 and picks[-1] > 383  # spread over the suite, not its head


def test_spread_takes_every_kth_in_order():
    items = list(range(360))
    assert budget.spread(items, 400) == items
    picked = budget.spread(items, 96)
    assert len(picked) == 96 and picked == sorted(picked) and picked[-1] > 350


def test_settings_refuse_bad_caps_by_name():
    for key, value, field in ((("heldout", "at_most"), 0, "heldout.at_most"), (("heads", "walks"), 2.5, "heads.walks")):
        s = fresh()
        s[key[0]][key[1]] = value
        with pytest.raises(SystemExit, match=field):
            wsettings.check(s)
