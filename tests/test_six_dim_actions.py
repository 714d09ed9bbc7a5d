"""A 6-dim Box action space with the continuous action search and phi's data metric: no grid of
3^6 candidates, actions in bounds, and both survive save/load (a few seconds)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium import spaces

from cme_agent import CMEPolicyIteration
from tests.test_defaults_contract import SMALL_BUDGETS, PointMass3D

MIXING = np.array([[1, 0, 0, 0.5, 0, 0], [0, 1, 0, 0, 0.5, 0], [0, 0, 1, 0, 0, 0.5]], np.float32)


class PointMassSixActuators(PointMass3D):
    """PointMass3D driven by six actuators with unequal bounds, mixed into its three forces."""

    action_space = spaces.Box(np.array([-1, -1, -1, -2, 0, -0.5], np.float32), np.array([1, 1, 1, 2, 1, 0.5], np.float32))

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        action = np.clip(action, self.action_space.low, self.action_space.high)
        return super().step(np.clip(MIXING @ action, -1.0, 1.0))


def test_six_dim_actions_search_continuously_with_the_data_metric_and_survive_save_load(tmp_path) -> None:
    kwargs = {
        **SMALL_BUDGETS,
        "policy_kwargs": {
            "phi": {"kind": "fourier", "metric": "data", "max_width": 100},
            "action_search": {"refine_steps": 5},
        },
    }
    model = CMEPolicyIteration("CMEPolicy", PointMassSixActuators(), seed=0, **kwargs).learn(400)
    policy = model.policy
    assert policy.candidates.shape[1] == 6 and len(policy.candidates) <= policy.action_search.n_samples + 1  # not 3^6 = 729
    assert model.dynamics.phi.follows_data and not model.dynamics.phi.needs_fit
    obs = np.random.default_rng(0).normal(0, 0.5, (64, 6)).astype(np.float32)
    actions, _ = model.predict(obs, deterministic=True)
    space = PointMassSixActuators.action_space
    assert np.all(actions >= space.low) and np.all(actions <= space.high)
    candidates = {tuple(row) for row in policy.candidates.numpy().round(6)}
    assert any(tuple(row) not in candidates for row in actions.round(6))  # the search left the candidates
    _, values = policy.greedy(torch.as_tensor(obs))
    best_candidate = policy.candidate_q_values(torch.as_tensor(obs)).max(dim=1).values
    assert bool((values >= best_candidate - 1e-5).all())  # never below the best candidate
    path = tmp_path / "six.zip"
    model.save(path)
    loaded = CMEPolicyIteration.load(path)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], actions)
    assert loaded.policy.action_search.refine_steps == 5
    torch.testing.assert_close(loaded.dynamics.phi.inv_std, model.dynamics.phi.inv_std)
