"""benchmarks/learning_quality.py: the report's statistics on curves built by hand, and a
Gymnasium id trained at the library's defaults through ``--env-id``'s path."""

from __future__ import annotations

import math

from benchmarks import learning_quality
from tests.conftest import small_kwargs


def _curve(returns: list[float], seconds: float = 10.0) -> list[dict]:
    return [
        {"steps": 1000 * (i + 1), "return_mean": r, "train_seconds": seconds, "n_features": 100} for i, r in enumerate(returns)
    ]


def test_summary_counts_reach_finals_and_the_worst_evaluation_after_the_target():
    curves = [
        _curve([-900, -190, -450, -180]),
        _curve([-800, -600, -300, -250]),
        _curve([-700, -650, -200, -170]),  # at the target exactly: reached
    ]
    row = learning_quality.summarise("pendulum", curves, target=-200)
    env, steps, target, reached, median, final, worst_seed, worst_after, per_seed, *_ = row
    assert (env, steps, target, reached, median) == ("pendulum", 4000, "-200", "2/3", "2500")
    assert final == "-200.0 +- 43.6" and worst_seed == "-250"
    assert worst_after == "-450"  # seed 0's collapse after it first reached -200
    assert per_seed == "-180, -250, -170"


def test_a_gymnasium_id_is_trained_and_evaluated_every_period():
    kwargs = small_kwargs(exploration={"random_steps": 100})
    rows = learning_quality.train_gym_id("Pendulum-v1", 3, kwargs, budget=300, period=100)
    assert [row["steps"] for row in rows] == [100, 200, 300]
    assert all(row["env"] == "Pendulum-v1" and row["seed"] == 3 for row in rows)
    assert all(math.isfinite(row["return_mean"]) and row["return_mean"] < 0 for row in rows)
    assert rows[-1]["n_features"] > 0
