"""benchmarks/fixed_model_planning.py: the report's counts on rows built by hand, and a short
run whose planning blocks leave the model untouched."""

from __future__ import annotations

import torch

from benchmarks.diagnostics import fixed_model_planning
from cme_agent import CMEPolicyIteration


def _curve(returns: list[float], biases: list[float]) -> list[dict]:
    return [
        {"block": b, "rounds": 5 * b, "return_mean": r, "value_bias": v, "changed": 0.1 * b}
        for b, (r, v) in enumerate(zip(returns, biases, strict=True))
    ]


def test_report_counts_moves_and_falls_with_a_rising_bias():
    curves = [
        _curve([-200, -250, -300], [0.1, 0.3, 0.5]),  # falls twice, the bias rising each time
        _curve([-300, -250, -240], [0.4, 0.2, 0.1]),  # up by 60
        _curve([-150, -160, -145], [0.0, 0.1, 0.0]),  # within 20
    ]
    text = fixed_model_planning.report("pendulum", curves, [0, 1, 2], ["run"], wall=1.0, workers=1)
    assert "up on 1 seeds, down on 1, within 20 on 1" in text
    assert "(change per seed: -100, +60, +5)" in text
    assert "in the 2 falls by more than 20 the bias rose in 2" in text
    assert "| mean +- std | -216.7 +- 62.4 | -220.0 +- 42.4 | -228.3 +- 63.8 |  |" in text


def test_planning_blocks_leave_the_model_and_the_data_untouched(monkeypatch):
    """Only the planner runs between measurements: B, psi and D are as training left them."""
    seen = {}
    build = fixed_model_planning.build_agent

    def keep(cfg, env):
        seen["model"] = build(cfg, env)
        return seen["model"]

    monkeypatch.setattr(fixed_model_planning, "build_agent", keep)
    overrides = ("agent.exploration.random_steps=100", "agent.evaluation.collection_size=300", "agent.evaluation.rounds=2")
    job = fixed_model_planning.Job("pendulum", 0, 200, 2, overrides, "unused")
    model_state = {}

    def snapshot_after_learn(self, *args, **kwargs):
        result = learn(self, *args, **kwargs)
        model_state.update(weights=self.dynamics.weights.clone(), q=self.q, stored=len(self.store))
        return result

    learn = CMEPolicyIteration.learn
    monkeypatch.setattr(CMEPolicyIteration, "learn", snapshot_after_learn)
    rows = fixed_model_planning.plan_on_fixed_model(job)
    model = seen["model"]
    assert [row["rounds"] for row in rows] == [0, 2, 4]
    assert rows[0]["changed"] == 0.0 and all(0.0 <= row["changed"] <= 1.0 for row in rows)
    assert torch.equal(model.dynamics.weights, model_state["weights"])
    assert (model.q, len(model.store)) == (model_state["q"], model_state["stored"])
    assert model.num_timesteps == 200
