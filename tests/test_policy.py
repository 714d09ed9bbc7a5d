"""Greedy action search, feature maps and bad input at construction."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces

from cme_agent import CMEPolicy, CMEPolicyIteration, RewardSpec
from cme_agent.config import ObservationConfig
from cme_agent.encoding import ObservationEncoder
from cme_agent.state_features import RBFGrid


def _policy(action_space, **kwargs):
    obs_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
    return CMEPolicy(obs_space, action_space, phi={"resolution": [5]}, **kwargs)


def _grow(policy, centres, bandwidths):
    """Append kernel features with zero model weights, as feature selection would."""
    policy.dynamics.grow(centres, bandwidths, torch.zeros(policy.dynamics.weights.shape[0], len(bandwidths)))


def test_greedy_discrete_enumerates_the_actions():
    policy = _policy(spaces.Discrete(4), reward=RewardSpec(lambda obs, a: (a == 2).float() - 0.1 * a.float()))
    actions, values = policy.greedy(torch.zeros(3, 2))
    assert actions.tolist() == [2, 2, 2]
    assert torch.allclose(values, torch.full((3,), 0.8))


def test_greedy_box_grid_and_refinement():
    target = 0.33
    reward = RewardSpec(lambda obs, a: -((a[:, 0] - target) ** 2))
    grid = _policy(spaces.Box(-2.0, 2.0, (1,), np.float32), action_search={"grid_size": 21}, reward=reward)
    actions, _ = grid.greedy(torch.zeros(2, 2))
    assert torch.all((actions[:, 0] - target).abs() <= 0.1)  # grid spacing 0.2
    refined = _policy(
        spaces.Box(-2.0, 2.0, (1,), np.float32),
        action_search={"grid_size": 21, "refine_steps": 30, "refine_lr": 0.005},
        reward=reward,
    )
    actions, _ = refined.greedy(torch.zeros(2, 2))
    assert torch.all((actions[:, 0] - target).abs() < 0.02)


def test_default_box_candidates_are_full_push_either_way_or_none():
    policy = _policy(spaces.Box(np.array([-3.0, 0.0], np.float32), np.array([3.0, 1.0], np.float32)))
    expected = {(a, b) for a in (-3.0, 0.0, 3.0) for b in (0.0, 0.5, 1.0)}
    assert {tuple(row) for row in policy.candidates.tolist()} == expected


def test_greedy_follows_the_psi_weights():
    policy = _policy(spaces.Box(-1.0, 1.0, (1,), np.float32), action_search={"grid_size": 21})
    # one kernel feature centred at state (0, 0) and normalised action 0.6, with a positive weight
    _grow(policy, torch.tensor([[0.0, 0.0, 0.6]]), torch.tensor([0.2]))
    policy.theta_psi = torch.ones(1)
    actions, _ = policy.greedy(torch.zeros(1, 2))
    assert float(actions[0, 0]) == pytest.approx(0.6, abs=1e-5)


def test_greedy_high_dimensional_box_uses_sampled_candidates():
    reward = RewardSpec(lambda obs, a: -(a**2).sum(1))
    policy = _policy(spaces.Box(-1.0, 1.0, (3,), np.float32), action_search={"n_samples": 64}, reward=reward)
    assert policy.candidates.shape == (65, 3)
    actions, _ = policy.greedy(torch.zeros(4, 2))
    assert torch.equal(actions, torch.zeros(4, 3))  # the centre is always a candidate


def test_grid_points_give_the_candidates_in_env_units():
    policy = _policy(spaces.Box(-2.0, 2.0, (2,), np.float32), action_search={"grid_points": [-1, -0.2, 0, 0.2, 1]})
    assert policy.candidates.shape == (25, 2)
    values = torch.tensor([-2.0, -0.4, 0.0, 0.4, 2.0])
    torch.testing.assert_close(policy.candidates[:5], torch.stack([torch.full((5,), -2.0), values], dim=1))
    reward = RewardSpec(lambda obs, a: -((a - 0.4) ** 2).sum(1))  # best at a small action the 3-point grid lacks
    small = _policy(
        spaces.Box(-2.0, 2.0, (1,), np.float32), action_search={"grid_points": [-1, -0.2, 0, 0.2, 1]}, reward=reward
    )
    torch.testing.assert_close(small.greedy(torch.zeros(3, 2))[0], torch.full((3, 1), 0.4))


def test_factorised_candidate_q_equals_paired_q():
    policy = _policy(spaces.Box(-1.0, 1.0, (2,), np.float32), action_search={"grid_size": 5})
    generator = torch.Generator().manual_seed(0)
    _grow(policy, torch.rand(30, 4, generator=generator) * 2 - 1, torch.rand(30, generator=generator) + 0.1)
    policy.theta_psi = torch.randn(30, generator=generator)
    policy.theta_phi = torch.randn(policy.dynamics.p, generator=generator)
    obs = torch.rand(6, 2, generator=generator) * 2 - 1
    table = policy.candidate_q_values(obs)
    for k, action in enumerate(policy.candidates):
        paired = policy.q_values(obs, action.expand(6, 2))
        assert torch.allclose(table[:, k], paired, atol=1e-5)


def test_rbf_grid_is_periodic_in_angles():
    space = spaces.Box(np.array([-1, -1, -8], np.float32), np.array([1, 1, 8], np.float32))
    phi = RBFGrid(ObservationEncoder(space, ObservationConfig(angle_pairs=((0, 1),))), (12, 5), 1.0)
    just_below, just_above = np.pi - 1e-4, -np.pi + 1e-4
    obs = torch.tensor([[np.cos(just_below), np.sin(just_below), 0.0], [np.cos(just_above), np.sin(just_above), 0.0]])
    features = phi(obs.float())
    assert features.shape == (2, 61)
    assert torch.allclose(features[0], features[1], atol=1e-3)
    assert torch.all(features[:, -1] == 1)  # the constant feature


@pytest.mark.parametrize(
    "env, message",
    [
        (gym.make("FrozenLake-v1"), "Box observation space"),
        (gym.make("Blackjack-v1"), "Box observation space"),
    ],
)
def test_unsupported_spaces_are_refused_by_name(env, message):
    with pytest.raises(ValueError, match=message):
        CMEPolicyIteration("CMEPolicy", env)


def test_unsupported_action_space_is_named():
    class MultiDiscreteEnv(gym.Env):
        observation_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        action_space = spaces.MultiDiscrete([2, 3])

        def reset(self, *, seed=None, options=None):
            return np.zeros(2, np.float32), {}

        def step(self, action):
            return np.zeros(2, np.float32), 0.0, False, False, {}

    with pytest.raises(ValueError, match=r"MultiDiscrete"):
        CMEPolicyIteration("CMEPolicy", MultiDiscreteEnv())


def test_infinite_observation_bounds_are_estimated_from_the_first_data():
    from gymnasium.envs.classic_control import CartPoleEnv

    unknown = gym.wrappers.TimeLimit(CartPoleEnv(), 500)  # no env id: no preset gives its velocity bounds
    encoder = CMEPolicyIteration("CMEPolicy", unknown).dynamics.obs_encoder
    assert encoder.needs_fit and encoder.fit_dims == [1, 3]
    with pytest.raises(RuntimeError, match=r'dims \[1, 3\] have no usable bounds.*policy_kwargs=\{"observation"'):
        encoder.normalize(torch.zeros(1, 4))


def test_known_envs_get_their_observation_facts():
    pendulum = CMEPolicyIteration("CMEPolicy", "Pendulum-v1")
    assert pendulum.policy.dynamics.obs_encoder.angle_pairs == [(0, 1)]
    assert pendulum.policy.dynamics.phi.width == 21 * 15 + 1  # its preset's angle x velocity grid
    cartpole = CMEPolicyIteration("CMEPolicy", "CartPole-v1")
    assert float(cartpole.policy.dynamics.obs_encoder.half_range[1]) == 3.0
    explicit = CMEPolicyIteration(
        "CMEPolicy", "Pendulum-v1", policy_kwargs={"observation": {"angle_pairs": []}, "phi": {"resolution": [5]}}
    )
    assert explicit.policy.dynamics.obs_encoder.angle_pairs == []


@pytest.mark.parametrize(
    "kwargs, key",
    [
        ({"gamma": 1.5}, "gamma"),
        ({"omega": -0.1}, "omega"),
        ({"steps_per_iteration": 0}, "steps_per_iteration"),
        ({"feature_selection": {"bandwidths": [0.3, -1.0]}}, "feature_selection.bandwidths"),
        ({"model_update": {"learning_rate": 3.0}}, "model_update.learning_rate"),
        ({"evaluation": {"rounds": 0}}, "evaluation.rounds"),
        ({"exploration": {"epsilon": 2}}, "exploration.epsilon"),
        ({"feature_selection": {"bandwith": 0.3}}, "unknown key"),
        ({"policy_kwargs": {"phi": {"resolution": [21, 15, 3]}, "observation": {"angle_pairs": [[0, 1]]}}}, "phi.resolution"),
    ],
)
def test_bad_hyperparameters_name_the_key(kwargs, key):
    with pytest.raises(ValueError, match=key):
        CMEPolicyIteration("CMEPolicy", "Pendulum-v1", **kwargs)


def test_custom_phi_module_is_used():
    phi = torch.nn.Linear(3, 8)
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", policy_kwargs={"phi": phi})
    assert model.policy.dynamics.phi.width == 9
    assert model.dynamics.phi_weights.shape == (9, 0)
