"""How `--hours` divides: the work that is not training is sized by the dataset and set
aside first (`settings.COSTS`), and the training stages still open share what is left by
their shares. Recomputed at every stage from the minutes really spent, so a stage that ran
long is paid for by the ones after it. NumPy-free and torch-free: read by tests as is."""

from __future__ import annotations

from . import settings as wsettings

TRAINING_STAGES = tuple(wsettings.BUDGET_SHARES)
# The stages whose minutes `COSTS["fixed_minutes"]` covers (the heads' export among them).
FIXED_STAGES = ("split", "from", "heads", "export", "parity", "card")


def pending(stages: dict, name: str) -> bool:
    return stages.get(name, {}).get("status", "pending") not in ("done", "skipped")


def open_training(stages: dict) -> list[str]:
    return [n for n in TRAINING_STAGES if pending(stages, n)]


def work_ahead(settings: dict, stages: dict, train: list[dict], held: list[dict]) -> dict[str, float]:
    """Expected minutes of the work that is not training and is not yet done, for the
    training and held-out walks of the split (each a list of index entries with `frames`)."""
    c = wsettings.COSTS
    frames = lambda walks: sum(t["frames"] for t in walks)
    ahead = {"exports and checks": c["fixed_minutes"] * sum(pending(stages, n) for n in FIXED_STAGES) / len(FIXED_STAGES)}
    if pending(stages, "autoencoder"):
        ahead["latent cache"] = frames(train) * c["encode_ms_per_frame"] / 60e3
    if pending(stages, "heads"):
        ahead["head data"] = frames(spread(train, settings["heads"]["walks"])) * c["head_data_ms_per_frame"] / 60e3
        ahead["head training"] = settings["heads"]["minutes"]
    if pending(stages, "eval"):
        limit = settings["eval"].get("limit")
        ahead["eval"] = frames(held[:limit] if limit else held) * c["eval_ms_per_frame"] / 60e3
    return ahead


def spent(stages: dict) -> float:
    """Every stage's minutes so far, over every sitting."""
    return sum(v.get("minutes", 0.0) for v in stages.values())


def training_pool(settings: dict, stages: dict, ahead: dict[str, float]) -> float:
    """Minutes the open training stages may still share: the budget, less every stage's
    minutes so far and the work ahead."""
    return max(0.0, settings["hours"] * 60 - spent(stages) - sum(ahead.values()))


def training_minutes(settings: dict, stages: dict, ahead: dict[str, float], name: str) -> float:
    """This stage's part of the pool, by its share among the training stages still open."""
    shares = wsettings.budget_shares(settings["device"])
    open_ = open_training(stages)
    if name not in open_ or shares[name] == 0:
        return 0.0
    return training_pool(settings, stages, ahead) * shares[name] / sum(shares[n] for n in open_)


def heldout_picks(count: int, held: dict) -> set[int]:
    """Which of `count` trajectories are held out: every k-th, so that each task and range
    keeps its share, within `at_least` and `at_most`."""
    n = min(held["at_most"], max(held["at_least"], round(held["share"] * count)))
    every = count / n
    return {int(i * every + every / 2) for i in range(n)}


def spread(items: list, n: int) -> list:
    """At most n of `items`, every k-th, in their order."""
    if len(items) <= n:
        return items
    every = len(items) / n
    return [items[int(i * every + every / 2)] for i in range(n)]
