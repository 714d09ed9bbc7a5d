"""cme_agent.dynamics.observation.ObservationModel: the fits on a known linear system, the two-sided
termination, the batched step, and its weights surviving a state_dict round trip."""

from __future__ import annotations

import numpy as np
import torch
from conftest import linear_system

from cme_agent.dynamics.observation import ObservationModel, logistic, quadratic


def fitted(n: int = 2000, seed: int = 0) -> ObservationModel:
    model = ObservationModel(4, 1)
    model.fit(linear_system(n, seed))
    return model


def test_the_model_recovers_a_linear_system() -> None:
    model, test = fitted(), linear_system(500, 1)
    np.testing.assert_allclose(model.next_obs(test.obs, test.actions).numpy(), test.next_obs.double().numpy(), atol=1e-4)
    # the reward is quadratic in s': the ridge on [z, z^2, 1, a, a^2, ...] holds it where s' is within the range
    # of the non-terminal transitions it was fitted on, and holds it at that range's edge beyond it
    predicted, rewards = model.reward(test.next_obs, test.actions), test.rewards.double()
    low, high = model.reward_range
    edge = model.z_range * model.std + model.mean  # (2, obs_dim) the range of s' of the fit
    within = ((test.next_obs >= edge[0]) & (test.next_obs <= edge[1])).all(dim=1)
    assert 400 <= within.sum() < 500  # the terminal transitions (|s'_1| > 0.15) are beyond it
    np.testing.assert_allclose(predicted[within].numpy(), rewards[within].clamp(low, high).numpy(), atol=1e-3)
    held = 1 - test.next_obs[:, 0].double().clamp(*edge[:, 0]).square()
    np.testing.assert_allclose(predicted[~within].numpy(), held[~within].clamp(low, high).numpy(), atol=1e-3)
    accuracy = ((model.terminates(test.next_obs) > 0.5) == test.terminated).double().mean()
    assert accuracy > 0.95  # a two-sided boundary: the quadratic features carry it


def test_a_two_sided_termination_needs_the_quadratic_features() -> None:
    data = linear_system(2000, 2)
    x = data.next_obs.double()
    affine = torch.cat([x, torch.ones(len(x), 1, dtype=x.dtype)], dim=1)
    linear, both = logistic(affine, data.terminated.double()), logistic(quadratic(x / x.std(dim=0)), data.terminated.double())
    accuracy_linear = ((affine @ linear > 0) == data.terminated).double().mean()
    accuracy_quadratic = ((quadratic(x / x.std(dim=0)) @ both > 0) == data.terminated).double().mean()
    assert accuracy_quadratic > 0.97 > accuracy_linear + 0.05


def test_the_step_pairs_every_state_with_every_candidate_state_major() -> None:
    model, obs = fitted(), linear_system(3, 5).obs
    candidates = torch.tensor([[-1.0], [0.0], [1.0]])
    next_obs, going_on, rewards = model.step(obs, candidates)
    assert next_obs.shape == (9, 4) and going_on.shape == rewards.shape == (9,)
    assert next_obs.dtype == going_on.dtype == rewards.dtype == torch.float32
    torch.testing.assert_close(next_obs[1 * 3 + 2], model.next_obs(obs[1:2], candidates[2:3])[0].float())
    assert ((going_on >= 0) & (going_on <= 1)).all()


def test_the_weights_survive_a_state_dict_round_trip() -> None:
    model, copy = fitted(), ObservationModel(4, 1)
    copy.load_state_dict(model.state_dict())
    obs, candidates = linear_system(5, 6).obs, torch.tensor([[-0.5], [0.5]])
    for mine, theirs in zip(model.step(obs, candidates), copy.step(obs, candidates), strict=True):
        torch.testing.assert_close(mine, theirs)
    assert not torch.equal(ObservationModel(4, 1).step(obs, candidates)[0], model.step(obs, candidates)[0])
