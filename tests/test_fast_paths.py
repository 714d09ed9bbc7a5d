"""The fast paths equal the reference computations to float32 tolerance: the kernel, the greedy
step (blocked, factorised, into reused buffers), acting, and the policy evaluation built on them."""

import dataclasses

import numpy as np
import pytest
import torch
from stable_baselines3.common.policies import BasePolicy

from cme_agent import CMEPolicyIteration
from cme_agent import policy as policy_module
from cme_agent.kernel_bank import CUTOFF_EXPONENT, gaussian_kernel
from cme_agent.planning import bellman_residual_weights


@pytest.fixture(scope="module")
def trained(request):
    """A Pendulum agent after a few iterations (q > 0), with a known reward, and a CartPole one
    (Discrete actions, a terminal bonus of 0 but a termination model)."""
    from tests.conftest import small_kwargs

    models = {}
    for env_id in ("Pendulum-v1", "CartPole-v1"):
        kwargs = small_kwargs() if env_id == "Pendulum-v1" else small_kwargs(policy_kwargs={"phi": {"resolution": [3]}})
        model = CMEPolicyIteration("CMEPolicy", env_id, seed=0, **kwargs)
        model.learn(400)
        assert model.q > 0
        models[env_id] = model
    return models


def test_kernel_equals_the_definition_in_float64():
    generator = torch.Generator().manual_seed(0)
    x, centres = torch.randn(300, 4, generator=generator), torch.randn(50, 4, generator=generator)
    a = torch.rand(50, generator=generator) * 20 + 0.1
    exact = torch.exp(-((x[:, None].double() - centres[None].double()) ** 2).sum(-1) * a.double())
    exact[exact <= np.exp(CUTOFF_EXPONENT)] = 0.0
    fast = gaussian_kernel(x, centres, a)
    assert torch.allclose(fast.double(), exact, atol=2e-6, rtol=0)
    assert (fast[exact == 0] == 0).all() and (fast >= 0).all() and (fast <= 1).all()
    out = torch.full((300, 50), float("nan"))
    assert torch.equal(gaussian_kernel(x, centres, a, out=out), fast) and torch.equal(out, fast)


@pytest.mark.parametrize("env_id", ["Pendulum-v1", "CartPole-v1"])
def test_greedy_step_equals_the_paired_computation(trained, env_id, monkeypatch):
    policy = trained[env_id].policy
    monkeypatch.setattr(policy_module, "BLOCK_ELEMENTS", 7 * policy.dynamics.q)  # many blocks, a ragged last one
    states = trained[env_id].draw_collection()[:100]
    step = policy.greedy_step(states)
    table = torch.stack(
        [policy.q_values(states, action.expand(len(states), *action.shape)) for action in policy.candidates], 1
    )
    assert torch.allclose(step.values, table.max(dim=1).values, atol=1e-4)
    assert torch.allclose(policy.q_values(states, step.actions), step.values, atol=1e-4)
    assert torch.allclose(step.psi, policy.dynamics.features(states, step.actions), atol=1e-6)
    assert torch.allclose(step.phi, policy.dynamics.phi(states))
    assert torch.equal(policy.act(states), step.actions)
    dynamics = policy.dynamics
    read = policy.greedy_step(states, dynamics.readout())  # psi read block by block, never stored
    assert torch.equal(read.actions, step.actions)
    next_phi, model_rewards = dynamics.read(read.phi, read.psi)
    reference_next_phi = step.psi @ dynamics.phi_weights.T + (step.phi if dynamics.feature_dynamics else 0)
    assert torch.allclose(next_phi, reference_next_phi, atol=1e-4)
    assert torch.allclose(model_rewards, dynamics.linear_reward(step.phi, step.psi), atol=1e-4)


@pytest.mark.parametrize("env_id", ["Pendulum-v1", "CartPole-v1"])
def test_policy_evaluation_equals_the_reference_in_float64(trained, env_id):
    model = trained[env_id]
    dynamics, gamma, l2 = model.dynamics, model.gamma, model.evaluation_config.l2
    states = model.draw_collection()
    weights = model.policy_evaluation(states)
    actions = model.policy.greedy(states)[0]
    phi = dynamics.phi(states).double()
    psi = dynamics.features(states, actions).double()
    next_phi = phi + psi @ dynamics.phi_weights.T.double()  # feature dynamics
    c_phi, c_psi = dynamics.reward_weights()
    rewards = dynamics.reward.step_reward(states, actions).double() + phi @ c_phi.double() + psi @ c_psi.double()
    reference = bellman_residual_weights(phi, next_phi, rewards, gamma, l2)
    values, reference_values = phi @ weights.double(), phi @ reference
    assert torch.linalg.vector_norm(values - reference_values) <= 1e-3 * torch.linalg.vector_norm(reference_values)


def test_short_predict_equals_sb3s(trained):
    for model in trained.values():
        obs = model.draw_collection()[:6].numpy()
        for observation in (obs, obs[0]):
            fast, _ = model.policy.predict(observation, deterministic=True)
            reference, _ = BasePolicy.predict(model.policy, observation, deterministic=True)
            assert fast.shape == reference.shape and fast.dtype == reference.dtype
            np.testing.assert_array_equal(fast, reference)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_runs_end_to_end():
    from tests.conftest import small_kwargs

    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, device="cuda", **small_kwargs())
    model.learn(300)
    assert model.dynamics.weights.device.type == "cuda" and model.q > 0
    action, _ = model.predict(np.zeros(3, np.float32), deterministic=True)
    assert action.shape == (1,)


def test_refined_greedy_step_reads_psi_at_the_refined_actions(trained, monkeypatch):
    agent = trained["Pendulum-v1"]
    policy = agent.policy
    monkeypatch.setattr(policy, "action_search", dataclasses.replace(policy.action_search, refine_steps=5, refine_lr=0.05))
    monkeypatch.setattr(policy_module, "BLOCK_ELEMENTS", 7 * policy.dynamics.q)
    states = agent.draw_collection()[:60]
    step = policy.greedy_step(states)
    assert not torch.isin(step.actions, policy.candidates).all()  # some actions moved off the candidate grid
    assert torch.allclose(step.psi, policy.dynamics.features(states, step.actions), atol=1e-6)
    readout = policy.dynamics.readout()
    assert torch.allclose(policy.greedy_step(states, readout).psi, step.psi @ readout, atol=1e-4)
