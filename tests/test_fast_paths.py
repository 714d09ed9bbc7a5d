"""The fast paths equal the reference computations to float32 tolerance: the kernel, the greedy
step (blocked, factorised, into reused buffers), acting, and the policy evaluation built on them."""

import dataclasses
import functools

import gymnasium
import numpy as np
import pytest
import torch
from stable_baselines3.common.policies import BasePolicy

from cme_agent import CMEPolicyIteration
from cme_agent import policy as policy_module
from cme_agent.config import ObservationConfig
from cme_agent.encoding import ObservationEncoder
from cme_agent.kernel_bank import CUTOFF_EXPONENT, gaussian_kernel
from cme_agent.planning import FactoredResidual, bellman_residual_weights, factored_dual_weights, factored_is_cheaper
from cme_agent.state_features import RBFGrid, StateFeatureMap


@pytest.fixture(scope="module")
def trained(request):
    """A Pendulum agent after a few iterations (q > 0), with a known reward, and a CartPole one
    (Discrete actions, a terminal bonus of 0 but a termination model). Their B is learned by SGD:
    the float32 tolerances below were measured on the evaluation systems of these models (an
    exact ridge fit of B on 360 transitions conditions them differently). CartPole's planner is pinned
    to the settings they were measured with (its preset's smoothed greedy step and gamma 0.99 before
    f15f1f5): the reference below evaluates the greedy policy."""
    from tests.conftest import small_kwargs

    models = {}
    sgd = {**small_kwargs()["model_update"], "method": "sgd"}
    greedy = {"gamma": 0.99, "improvement": {"method": "smoothed_greedy"}}
    for env_id in ("Pendulum-v1", "CartPole-v1"):
        kwargs = (
            small_kwargs() if env_id == "Pendulum-v1" else small_kwargs(policy_kwargs={"phi": {"resolution": [3]}}, **greedy)
        )
        model = CMEPolicyIteration("CMEPolicy", env_id, seed=0, **{**kwargs, "model_update": sgd})
        model.learn(400)
        assert model.q > 0
        models[env_id] = model
    # |C| = 300 < p = 626: the dual system, built from the factors of the residual map
    wide_kwargs = small_kwargs(policy_kwargs={"phi": {"resolution": [5]}}, model_update=sgd, **greedy)
    wide = CMEPolicyIteration("CMEPolicy", "CartPole-v1", seed=0, **wide_kwargs)
    wide.learn(400)
    assert wide.evaluator.factored(wide.dynamics, 300)
    models["CartPole-v1 factored"] = wide
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
    # act() builds psi in other blocks, whose products round differently: its actions are maximisers to rounding
    assert torch.allclose(policy.q_values(states, policy.act(states)), step.values, atol=1e-4)
    dynamics = policy.dynamics
    read = policy.greedy_step(states, dynamics.readout())  # psi read block by block, never stored
    assert torch.equal(read.actions, step.actions)
    next_phi, model_rewards = dynamics.read(read.phi, read.psi)
    reference_next_phi = step.psi @ dynamics.phi_weights.T + (step.phi if dynamics.feature_dynamics else 0)
    assert torch.allclose(next_phi, reference_next_phi, atol=1e-4)
    assert torch.allclose(model_rewards, dynamics.linear_reward(step.phi, step.psi), atol=1e-4)


# the factored model's dual system (|C| = 300 < p = 626) is ill-conditioned: on its collections the
# dense float32 path errs by 0.9e-3 to 8.5e-3 against the float64 reference, the factored one by 1.2e-3 to 2.0e-3
@pytest.mark.parametrize("env_id, tolerance", [("Pendulum-v1", 1e-3), ("CartPole-v1", 1e-3), ("CartPole-v1 factored", 5e-3)])
def test_policy_evaluation_equals_the_reference_in_float64(trained, env_id, tolerance):
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
    scale = torch.linalg.vector_norm(reference_values)
    # float32's own rounding of this system, which depends on the BLAS's code path (CartPole: 0.57e-3
    # of the values with MKL's AVX2 kernels, 1.03e-3 with its AVX-512 ones): the plain float32 solve
    plain = phi @ bellman_residual_weights(phi.float(), next_phi.float(), rewards.float(), gamma, l2).double()
    floor = torch.linalg.vector_norm(plain - reference_values) / scale
    assert torch.linalg.vector_norm(values - reference_values) <= max(tolerance, 2 * float(floor)) * scale


def _grid(resolution, periodic_pairs=()):
    space = gymnasium.spaces.Box(-2.0, 2.0, (2 * len(periodic_pairs) + len(resolution) - len(periodic_pairs),))
    encoder = ObservationEncoder(space, ObservationConfig(angle_pairs=[list(pair) for pair in periodic_pairs]))
    return RBFGrid(encoder, tuple(resolution), 0.7), space


@pytest.mark.parametrize("resolution, pairs", [((5, 7, 9), ()), ((8, 4), ((0, 1),)), ((6,), ())])
def test_rbf_grid_equals_its_definition_and_its_gram_the_product(resolution, pairs):
    grid, space = _grid(resolution, pairs)
    space.seed(0)
    obs = torch.as_tensor(np.stack([space.sample() for _ in range(300)]))
    if pairs:  # a (cos, sin) pair
        angle = obs[:, 0] * np.pi
        obs[:, 0], obs[:, 1] = torch.cos(angle), torch.sin(angle)
    phi = grid(obs)
    reference = torch.ones(len(obs), 1, dtype=torch.float64)  # the tensor product, first dimension slowest
    for bumps in grid.bumps(obs):
        reference = (reference[:, :, None] * bumps.double()[:, None, :]).flatten(1)
    assert torch.allclose(phi[:, :-1].double(), reference, rtol=1e-5, atol=1e-7) and (phi[:, -1] == 1).all()
    blocks = torch.arange(len(obs)) // 256
    on_or_below = blocks[:, None] >= blocks[None, :]
    exact = (phi.double() @ phi.double().T) * 0.3
    assert torch.allclose(grid.gram(obs, scale=0.3)[on_or_below], exact[on_or_below], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("with_states", [True, False])
def test_successor_targets_equal_phi_of_the_successors_less_phi(with_states):
    grid, space = _grid((5, 7, 9))
    space.seed(1)
    obs, next_obs = (torch.as_tensor(np.stack([space.sample() for _ in range(200)])) for _ in range(2))
    continuation = (torch.arange(200) % 7 != 0).float()
    reference = grid(next_obs) * continuation[:, None] - (grid(obs) if with_states else 0)
    fused = grid.successor_targets(next_obs, continuation, obs if with_states else None)
    assert torch.allclose(fused, reference, atol=1e-6)
    generic = StateFeatureMap.successor_targets(grid, next_obs, continuation, obs if with_states else None)
    assert torch.allclose(generic, reference, atol=1e-6)


@pytest.mark.parametrize("keeps_phi", [True, False])
def test_factored_dual_weights_equal_the_dense_solve(keeps_phi):
    """A = a Phi - Psi M^T in its factors gives the dense dual solve's w: equal in float64, and in
    float32 within the float32 tolerance of the dense path against the float64 reference."""
    grid, space = _grid((5, 7, 9))
    space.seed(2)
    states = torch.as_tensor(np.stack([space.sample() for _ in range(250)]))
    generator = torch.Generator().manual_seed(3)
    psi = torch.rand(250, 40, generator=generator) * torch.rand(250, 1, generator=generator)
    transition = torch.randn(grid.width, 40, generator=generator) * 0.05
    rewards = torch.randn(250, generator=generator)
    phi, gamma, l2 = grid(states), 0.95, 1e-4
    next_phi = psi.double() @ transition.double().T + (phi.double() if keeps_phi else 0)
    reference = bellman_residual_weights(phi.double(), next_phi, rewards.double(), gamma, l2)
    phi64 = phi.double()
    exact = factored_dual_weights(
        FactoredResidual(phi64, lambda scale: (phi64 @ phi64.T) * scale, psi.double(), transition.double(), gamma, keeps_phi),
        rewards.double(),
        l2,
    )
    assert torch.allclose(exact, reference, rtol=1e-6, atol=1e-8 * float(reference.abs().max()))
    gram = functools.partial(grid.gram, states)  # from the grid's factors
    fast = factored_dual_weights(FactoredResidual(phi, gram, psi, transition, gamma, keeps_phi), rewards, l2)
    dense = bellman_residual_weights(phi, next_phi.float(), rewards, gamma, l2)  # the dense float32 path

    def value_error(weights: torch.Tensor) -> float:
        values, reference_values = phi.double() @ weights.double(), phi.double() @ reference
        return float(torch.linalg.vector_norm(values - reference_values) / torch.linalg.vector_norm(reference_values))

    # an ill-conditioned problem: float32 products err by 0.3-1.8% on the dense path, 0.07-0.5% here
    assert fast.dtype == torch.float32 and value_error(fast) <= min(value_error(dense), 1e-2)
    residual = FactoredResidual(phi, gram, psi, transition, gamma, keeps_phi)
    dense_residual = phi.double() - gamma * next_phi
    assert torch.allclose(residual.matvec(fast).double(), dense_residual @ fast.double(), rtol=1e-4, atol=1e-4)


def test_the_factored_form_is_taken_where_it_costs_fewer_flops():
    assert factored_is_cheaper(2000, 2836, 339)  # CartPole's preset at 2,000 steps
    assert not factored_is_cheaper(2000, 2836, 900)  # 2 q (n^2 + n q + p q) = 12.6 G > n^2 p = 11.3 G
    assert not factored_is_cheaper(8000, 316, 10)  # the primal case: no dual system at all


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
    assert torch.allclose(step.values, policy.q_values(states, step.actions), atol=1e-4)  # refined block by block
    readout = policy.dynamics.readout()
    assert torch.allclose(policy.greedy_step(states, readout).psi, step.psi @ readout, atol=1e-4)
