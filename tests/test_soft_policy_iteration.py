"""KL-regularised (soft) policy iteration, ``improvement.method="soft"``: the soft policy, its
evaluation, the running average of the Q estimates, and the contrast with the smoothed greedy
step on small finite MDPs with an exact model."""

import numpy as np
import pytest
import torch
from gymnasium import spaces

from cme_agent import CMEPolicy, CMEPolicyIteration, RewardSpec
from cme_agent.config import ImprovementConfig
from cme_agent.planning import (
    action_spread,
    bellman_residual_weights,
    expected_candidate_features,
    softmax_policy,
)

SOFT = {"method": "soft"}


# ---------------------------------------------------------------------- a finite MDP as a CMEPolicy
def _finite_mdp(n_states: int, n_actions: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Random transitions P (n, K, n) and rewards R (n, K), float64."""
    generator = torch.Generator().manual_seed(seed)
    transitions = torch.rand(n_states, n_actions, n_states, generator=generator, dtype=torch.float64) ** 3
    transitions /= transitions.sum(-1, keepdim=True)
    return transitions, torch.randn(n_states, n_actions, generator=generator, dtype=torch.float64)


def _mdp_policy(transitions, rewards, features=None, improvement=None, feature_dynamics=True):
    """A float64 CMEPolicy whose model is exact on the finite MDP: state s is the observation
    x_s on a grid of [-1, 1], phi(x_s) = features[s] (one-hot by default) plus the constant, and
    psi has one kernel per (s, a), centred there and so narrow that psi(s, a) is one-hot. B's
    column of (s, a) is then E[phi(S') | s, a] (- phi(s)) exactly.

    :return: the policy and the (n, 1) observations of the states
    """
    n, k, _ = transitions.shape
    features = torch.eye(n, dtype=torch.float64) if features is None else features

    def index(obs):
        return ((obs[:, 0] + 1) / 2 * (n - 1)).round().long()

    reward = RewardSpec(lambda obs, a: rewards.to(obs.dtype)[index(obs), a.long()])
    policy = CMEPolicy(
        spaces.Box(-1.0, 1.0, (1,), np.float32),
        spaces.Discrete(k),
        phi=lambda obs: features.to(obs.dtype)[index(obs)],
        feature_dynamics=feature_dynamics,
        reward=reward,
        improvement=improvement,
    ).double()
    positions = torch.linspace(-1, 1, n, dtype=torch.float64)
    centres = torch.cat([positions.repeat_interleave(k)[:, None], torch.eye(k, dtype=torch.float64).repeat(n, 1)], 1)
    full = torch.cat([features, torch.ones(n, 1, dtype=torch.float64)], 1)  # phi with its constant
    weights = torch.stack(
        [transitions[s, a] @ full - (full[s] if feature_dynamics else 0) for s in range(n) for a in range(k)], 1
    )
    policy.dynamics.grow(centres, torch.full((n * k,), 0.02, dtype=torch.float64), weights)
    return policy, positions[:, None]


def _exact_value(transitions, rewards, probabilities, gamma):
    """V^pi = (I - gamma P_pi)^{-1} r_pi of a stochastic policy (n, K)."""
    p_pi = torch.einsum("sa,sat->st", probabilities, transitions)
    r_pi = (probabilities * rewards).sum(1)
    return torch.linalg.solve(torch.eye(len(r_pi), dtype=torch.float64) - gamma * p_pi, r_pi)


def _evaluate(policy, states, gamma, solver=bellman_residual_weights):
    """What CMEPolicyIteration.policy_evaluation does: the value weights of the current policy
    on C under the model, and the policy's probabilities (one-hot for the greedy one)."""
    dynamics = policy.dynamics
    if policy.soft:
        step = policy.soft_step(states)
        probabilities = step.probabilities
        rewards = step.step_rewards + dynamics.linear_reward(step.phi, step.psi)
    else:
        step = policy.greedy_step(states)
        probabilities = torch.nn.functional.one_hot(step.actions, len(policy.candidates)).double()
        rewards = dynamics.expected_reward(states, step.actions, step.phi, step.psi)
    weights = solver(step.phi, dynamics.expected_next_phi(step.phi, step.psi), rewards, gamma, 1e-12)
    return weights, probabilities, step.phi @ weights


def _policy_values(transitions, rewards, improvement, features, rounds=30, gamma=0.9, omega=0.5):
    """The exact mean value over the states of each policy pi_1 .. pi_rounds of the iteration."""
    policy, states = _mdp_policy(transitions, rewards, features, improvement)
    values = []
    for _ in range(rounds):
        weights, probabilities, _ = _evaluate(policy, states, gamma)
        values.append(float(_exact_value(transitions, rewards, probabilities, gamma).mean()))
        policy.improve(weights, gamma, omega, states)
    return np.array(values)


# ---------------------------------------------------------------------- tests
@pytest.mark.parametrize("feature_dynamics", [True, False])
def test_soft_evaluation_recovers_the_exact_value_of_a_finite_mdp(feature_dynamics):
    gamma = 0.9
    transitions, rewards = _finite_mdp(6, 3, seed=0)
    policy, states = _mdp_policy(transitions, rewards, improvement=SOFT, feature_dynamics=feature_dynamics)
    generator = torch.Generator().manual_seed(1)
    policy.theta_psi = torch.randn(policy.dynamics.q, generator=generator, dtype=torch.float64)
    policy.inverse_temperature = torch.tensor(0.7, dtype=torch.float64)  # a genuinely stochastic policy
    _, probabilities, value = _evaluate(policy, states, gamma, bellman_residual_weights)
    assert probabilities.max() < 0.99 and probabilities.min() > 1e-3
    exact = _exact_value(transitions, rewards, probabilities, gamma)
    assert torch.allclose(value, exact, atol=1e-8)


def test_expected_features_are_the_probability_weighted_sum():
    generator = torch.Generator().manual_seed(0)
    state_factor, action_factor = torch.rand(5, 8, generator=generator), torch.rand(4, 8, generator=generator)
    probabilities = softmax_policy(torch.randn(5, 4, generator=generator), 2.0)
    reference = sum(probabilities[:, [a]] * state_factor * action_factor[a] for a in range(4))
    assert torch.allclose(expected_candidate_features(state_factor, action_factor, probabilities), reference, atol=1e-6)


def _random_policy(improvement=SOFT, seed=0, q=40):
    """A Box(2) policy with a grown bank, a learned-reward model and random Q weights."""
    policy = CMEPolicy(
        spaces.Box(-1.0, 1.0, (2,), np.float32),
        spaces.Box(-1.0, 1.0, (1,), np.float32),
        phi={"resolution": [5]},
        action_search={"grid_size": 9},
        reward=RewardSpec(lambda obs, a: -((a[:, 0] - 0.3 * obs[:, 0]) ** 2)),
        improvement=improvement,
    )
    generator = torch.Generator().manual_seed(seed)
    grow(policy, q, generator)
    policy.theta_psi = 3 * torch.randn(q, generator=generator)
    policy.theta_phi = torch.randn(policy.dynamics.p, generator=generator)
    return policy, torch.rand(50, 2, generator=generator) * 2 - 1


def grow(policy, count, generator):
    """Append ``count`` kernel features with random model weights, as feature selection would."""
    dynamics = policy.dynamics
    centres = torch.rand(count, 3, generator=generator) * 2 - 1
    weights = 0.1 * torch.randn(dynamics.weights.shape[0], count, generator=generator)
    dynamics.grow(centres, torch.rand(count, generator=generator) * 0.4 + 0.2, weights)


def test_soft_step_equals_the_paired_computation():
    policy, obs = _random_policy()
    policy.inverse_temperature = torch.tensor(1.5)
    step = policy.soft_step(obs)
    table = policy.candidate_q_values(obs)
    probabilities = torch.softmax(1.5 * table, dim=1)
    assert torch.allclose(step.probabilities, probabilities, atol=1e-6)
    assert torch.allclose(policy.probabilities(obs), probabilities, atol=1e-6)
    paired_psi = sum(
        probabilities[:, [k]] * policy.dynamics.features(obs, a.expand(len(obs), 1)) for k, a in enumerate(policy.candidates)
    )
    assert torch.allclose(step.psi, paired_psi, atol=1e-5)
    readout = torch.randn(policy.dynamics.q, 3)
    assert torch.allclose(policy.soft_step(obs, readout).psi, paired_psi @ readout, atol=1e-4)
    step_rewards = policy.dynamics.reward.step_reward(obs.repeat_interleave(9, 0), policy.candidates.repeat(len(obs), 1))
    assert torch.allclose(step.step_rewards, (probabilities * step_rewards.reshape(-1, 9)).sum(1), atol=1e-6)
    assert torch.allclose(step.values, (probabilities * table).sum(1), atol=1e-4)


@pytest.mark.parametrize("beta", [0.0, 1e-3, 1.0, 1e4, float("inf")])
def test_soft_probabilities_lie_on_the_simplex(beta):
    policy, obs = _random_policy()
    policy.theta_psi = policy.theta_psi * 1e3  # Q values of order 1e3: beta * Q overflows without the shift
    policy.inverse_temperature = torch.tensor(beta)
    probabilities = policy.soft_step(obs).probabilities
    assert torch.isfinite(probabilities).all() and (probabilities >= 0).all()
    assert torch.allclose(probabilities.sum(1), torch.ones(len(obs)), atol=1e-5)
    if beta == 0.0:
        assert torch.allclose(probabilities, torch.full_like(probabilities, 1 / 9))


def test_infinite_beta_gives_the_greedy_policy():
    policy, obs = _random_policy()
    greedy = policy.greedy_step(obs)
    best = (policy.candidates[None, :, 0] == greedy.actions).float()  # (N, K) one-hot of greedy's action
    for beta, atol in ((float("inf"), 0.0), (1e6, 1e-5)):
        policy.inverse_temperature = torch.tensor(beta)
        soft = policy.soft_step(obs)
        assert torch.allclose(soft.probabilities, best, atol=atol)
        assert torch.allclose(soft.psi, greedy.psi, atol=1e-5)
        assert torch.allclose(soft.values, greedy.values, atol=1e-4)
    assert torch.equal(policy.act(obs), greedy.actions)  # acting: the argmax of the summed Q


@pytest.mark.parametrize("decay", [1.0, 0.7])
def test_summed_q_weights_zero_pad_as_psi_grows(decay):
    """n_k Qbar_k = sum_j decay^{k-j} Q^_j (the plain sum k Qbar_k without decay), each Q^_j
    read on the bank of its time: psi only appends, so the old weights are zero-padded."""
    policy, obs = _random_policy(improvement={**SOFT, "beta": 0.5, "decay": decay}, q=10)
    policy.theta_psi, policy.theta_phi = torch.zeros(0), torch.zeros(policy.dynamics.p)
    generator = torch.Generator().manual_seed(3)
    summed, count, gamma = 0.0, 0.0, 0.9
    for k, added in enumerate((0, 7, 0, 12), start=1):
        grow(policy, added, generator)
        weights = torch.randn(policy.dynamics.p, generator=generator)
        theta_phi, theta_psi = policy.dynamics.backup_weights(weights, gamma)
        psi = torch.stack([policy.dynamics.features(obs, a.expand(len(obs), 1)) for a in policy.candidates], 1)
        estimate = policy._candidate_step_rewards(obs) + (policy.dynamics.phi(obs) @ theta_phi)[:, None] + psi @ theta_psi
        summed, count = decay * summed + estimate, decay * count + 1
        policy.improve(weights, gamma, omega=0.5, states=obs)  # omega is not used by the soft improvement
        assert policy.theta_psi.shape == (policy.dynamics.q,)
        assert float(policy.improvements) == pytest.approx(count) and (decay < 1 or count == k)
        spread = float(action_spread(policy.candidate_q_values(obs)))
        assert float(policy.inverse_temperature) == pytest.approx(0.5 * count / spread, rel=1e-5)
        assert torch.allclose(count * policy.candidate_q_values(obs), summed, atol=1e-3)
        # pi_{k+1} proportional to exp(beta / sigma_k sum_j decay^{k-j} Q^_j)
        assert torch.allclose(policy.probabilities(obs), torch.softmax(0.5 * summed / spread, 1), atol=1e-5)


def test_spread_scale_makes_beta_free_of_the_reward_unit():
    """beta_k = beta k / sigma(Qbar_k): rescaling the rewards leaves pi unchanged."""
    transitions, rewards = _finite_mdp(6, 3, seed=4)
    probabilities = []
    for unit in (1.0, 1000.0):
        policy, states = _mdp_policy(transitions, unit * rewards, improvement={**SOFT, "beta": 0.3, "decay": 1.0})
        for _ in range(3):
            weights, _, _ = _evaluate(policy, states, 0.9)
            policy.improve(weights, 0.9, 0.5, states)
        sigma = action_spread(policy.candidate_q_values(states))
        assert float(policy.inverse_temperature) == pytest.approx(0.3 * 3 / float(sigma))
        probabilities.append(policy.soft_step(states).probabilities)
    assert torch.allclose(probabilities[0], probabilities[1], atol=1e-6)
    with pytest.raises(ValueError, match="states="):
        policy.improve(weights, 0.9, 0.5)


def test_action_spread_is_floored():
    constant = torch.full((4, 3), -7.0)
    assert float(action_spread(constant)) == pytest.approx(7e-6)  # SPREAD_FLOOR * rms
    assert float(action_spread(torch.zeros(4, 3))) == pytest.approx(1e-12)
    assert float(action_spread(torch.tensor([[0.0, 2.0], [1.0, 1.0]]))) == pytest.approx(np.sqrt(0.5))


# seeds of (8 states, 3 actions, 3 random features of phi) where the smoothed greedy step drops
GREEDY_DROPS = {6: -0.071, 10: -0.101, 25: -0.020}


def _coarse_features(seed: int) -> torch.Tensor:
    return torch.randn(8, 3, generator=torch.Generator().manual_seed(100 + seed), dtype=torch.float64)


@pytest.mark.parametrize("soft_config", [SOFT, {**SOFT, "decay": 1.0, "beta": 0.1}], ids=["defaults", "plain_sum"])
@pytest.mark.parametrize("seed", sorted(GREEDY_DROPS))
def test_soft_iteration_value_never_drops_while_the_greedy_one_does(seed, soft_config):
    """An exact model (B psi = E[phi(S') | s, a]) but phi coarser than the states, as in every
    continuous env: the Bellman-residual value is approximate, and the greedy step on it
    (smoothed, omega = 0.5) makes the policy value drop; the soft step does not."""
    transitions, rewards = _finite_mdp(8, 3, seed)
    features = _coarse_features(seed)
    greedy = _policy_values(transitions, rewards, None, features)
    soft = _policy_values(transitions, rewards, soft_config, features)
    assert np.diff(greedy).min() == pytest.approx(GREEDY_DROPS[seed], abs=1e-3)
    assert np.diff(soft).min() >= -1e-9
    assert soft[-1] > soft[0]


@pytest.mark.parametrize("seed", range(5))
def test_soft_iteration_is_monotone_with_an_exact_value(seed):
    """One-hot phi: exact evaluation, so pi_{k+1} proportional to pi_k exp(eta Q^{pi_k}) (the
    plain sum, decay 1) improves every state (mirror descent)."""
    transitions, rewards = _finite_mdp(6, 3, seed)
    values = _policy_values(transitions, rewards, {**SOFT, "decay": 1.0}, None, rounds=20)
    assert np.diff(values).min() >= -1e-9


def test_soft_improvement_config_is_checked():
    with pytest.raises(ValueError, match=r"improvement.method='greedy' is invalid"):
        ImprovementConfig(method="greedy")
    with pytest.raises(ValueError, match=r"improvement.beta=0 is invalid"):
        ImprovementConfig(method="soft", beta=0)
    with pytest.raises(ValueError, match=r"improvement.decay=0 is invalid"):
        ImprovementConfig(decay=0)
    with pytest.raises(ValueError, match=r"action_search.refine_steps=3 is invalid with improvement.method='soft'"):
        CMEPolicyIteration("CMEPolicy", "Pendulum-v1", improvement=SOFT, policy_kwargs={"action_search": {"refine_steps": 3}})


def _decayed_count(k: int) -> float:
    """n_k = decay n_{k-1} + 1 with the default decay, after k improvements (4 iterations of 2 rounds: 8)."""
    decay = ImprovementConfig().decay
    return (1 - decay**k) / (1 - decay)


def test_soft_learn_save_load_predict(tmp_path, pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, improvement=SOFT, **pendulum_kwargs)
    model.learn(400)
    policy = model.policy
    assert model.q > 0 and float(policy.inverse_temperature) > 0
    assert float(policy.improvements) == pytest.approx(_decayed_count(8))
    assert policy.theta_psi.shape[0] <= model.q
    model.save(tmp_path / "soft.zip")
    loaded = CMEPolicyIteration.load(tmp_path / "soft.zip")
    assert loaded.improvement_config == ImprovementConfig(method="soft")
    for name in ("theta_phi", "theta_psi", "improvements", "inverse_temperature"):
        assert torch.equal(getattr(loaded.policy, name), getattr(policy, name)), name
    rng = np.random.default_rng(0)
    angles = rng.uniform(-np.pi, np.pi, 64)
    obs = np.stack([np.cos(angles), np.sin(angles), rng.uniform(-8, 8, 64)], 1).astype(np.float32)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    states = torch.as_tensor(obs)
    assert torch.equal(loaded.policy.soft_step(states).probabilities, policy.soft_step(states).probabilities)
    torch.manual_seed(0)
    drawn = loaded.predict(obs, deterministic=False)[0]
    assert np.isin(drawn, policy.candidates.numpy()).all() and not np.array_equal(
        drawn, loaded.predict(obs, deterministic=True)[0]
    )
    resumed = CMEPolicyIteration.load(tmp_path / "soft.zip", env=model.get_env())
    resumed.learn(200, reset_num_timesteps=False)
    assert float(resumed.policy.improvements) == pytest.approx(_decayed_count(12))
    assert resumed.policy.theta_psi.shape[0] <= resumed.q


def test_a_policy_saved_before_the_soft_improvement_loads():
    """State dicts without ``improvements`` and ``inverse_temperature`` (older model files) load strictly, as k = 0."""
    policy, _ = _random_policy(improvement=None)
    state = policy.state_dict()
    for name in ("improvements", "inverse_temperature"):
        del state[name]
    fresh, _ = _random_policy(improvement=None, seed=1)
    fresh.load_state_dict(state, strict=True)
    assert torch.equal(fresh.theta_psi, policy.theta_psi) and float(fresh.improvements) == 0
