"""model_update.kind="observation": the LookaheadPlanner's depth, its eq. (7) through the model,
and the agent that plans and acts through it (Discrete and 6-dim Box actions, save/load, the
settings it refuses)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
import torch
from conftest import CARTPOLE_POLICY, PENDULUM_POLICY, small_kwargs
from gymnasium import spaces
from stable_baselines3.common.logger import Logger

from cme_agent import CMEPolicy, CMEPolicyIteration
from cme_agent.buffer import Transitions
from cme_agent.config import LOOKAHEAD_REFINE_STEPS
from cme_agent.lookahead import LookaheadPlanner, default_depth
from cme_agent.pictures import PICTURE_TAGS, agent_pictures, holdout_errors
from cme_agent.rewards import RewardSpec
from cme_agent.state_features import StateFeatureMap
from tests.test_defaults_contract import SMALL_BUDGETS
from tests.test_six_dim_actions import PointMassSixActuators

CANDIDATES = torch.tensor([[-1.0], [0.0], [1.0]])


def drift_data(n: int = 500, seed: int = 0) -> Transitions:
    """s' = s + a in one dim, never terminating."""
    generator = torch.Generator().manual_seed(seed)
    obs, actions = torch.rand(n, 1, generator=generator) * 4 - 2, torch.rand(n, 1, generator=generator) * 2 - 1
    return Transitions(obs, actions, torch.zeros(n), obs + actions, torch.zeros(n, dtype=torch.bool))


def planner(depth: int, reward: RewardSpec, width: int = 1) -> LookaheadPlanner:
    lookahead = LookaheadPlanner(1, spaces.Box(-1.0, 1.0, (1,)), width, depth, 0.95, reward)
    lookahead.fit(drift_data())
    return lookahead


class Ones(StateFeatureMap):
    """phi = 1: V is the constant w."""

    width = 1

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.ones(len(obs), 1)


ones = Ones()


def test_the_default_depth_is_three_where_its_leaves_are_few() -> None:
    assert [default_depth(k) for k in (2, 3, 9, 10, 11, 257)] == [3, 3, 3, 3, 1, 1]


@pytest.mark.parametrize(("depth", "action"), [(1, 0.0), (2, 1.0), (3, 1.0)])
def test_looking_ahead_pays_a_cost_now_for_a_reward_later(depth: int, action: float) -> None:
    # r(s, a) = s - a^2 / 2 from s = 0 with V = 0 at the leaves: greedy keeps still; two steps
    # ahead, pushing (-1/2 now) reaches s = 1, worth gamma * 1 = 0.95 at the next step
    reward = RewardSpec(lambda obs, a: obs[:, 0] - 0.5 * a[:, 0] ** 2)
    chosen = planner(depth, reward).greedy(ones, torch.zeros(2, 1), CANDIDATES)[0]
    assert chosen.tolist() == [[action], [action]]


class Quadratic(StateFeatureMap):
    """phi = [1, s, s^2]."""

    width = 3

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.cat([torch.ones(len(obs), 1), obs, obs.square()], dim=1)


def test_the_best_path_open_loop_has_the_trees_value_and_its_slope_in_the_first_action() -> None:
    # the refinement ascends the best path's value with its later actions held: at the path's first action it is
    # the tree's L_d, and where the best path does not switch its slope is L_d's (the envelope theorem)
    candidates = torch.linspace(-1, 1, 5).unsqueeze(1)
    lookahead = planner(3, RewardSpec(lambda obs, a: -((obs[:, 0] - 0.3) ** 2) - 0.4 * a[:, 0] ** 2), width=3)
    lookahead.value_weights = torch.tensor([0.5, 0.2, -0.3])
    quadratic, obs = Quadratic(), torch.linspace(-2, 2, 9).unsqueeze(1)
    actions, values, later = lookahead.greedy(quadratic, obs, candidates)
    assert later.shape == (9, 2, 1) and bool((later != 0).any())  # later steps that move the state
    torch.testing.assert_close(lookahead.action_values(quadratic, obs, actions, later), values, atol=1e-5, rtol=0)

    def closed_loop(first: torch.Tensor) -> torch.Tensor:
        next_obs, going_on, rewards = lookahead.transition(obs, first)
        return rewards + 0.95 * going_on * lookahead.backed_up_paths(quadratic, next_obs, candidates, 1)[0].max(dim=1).values

    def open_loop(path: torch.Tensor) -> Callable[[torch.Tensor], torch.Tensor]:
        return lambda first: lookahead.action_values(quadratic, obs, first, path)

    h = 1e-3
    tree, best_path, held_still = (
        (value(actions + h) - value(actions - h)) / (2 * h)
        for value in (closed_loop, open_loop(later), open_loop(torch.zeros_like(later)))
    )
    torch.testing.assert_close(best_path, tree, atol=2e-3, rtol=0)
    assert bool((held_still - tree).abs().max() > 0.5)  # the later actions matter: holding the state still is off


def test_eq7_through_the_model_values_a_constant_reward_at_its_discounted_sum() -> None:
    never = RewardSpec(lambda obs, a: torch.ones(len(obs)), 0.0, lambda obs: obs[:, 0] > 100)  # known: it never ends
    lookahead = planner(1, never)
    states = torch.linspace(-1, 1, 200).unsqueeze(1)
    weights = lookahead.evaluate(ones, states, CANDIDATES, 1e-6, Logger(None, []))
    np.testing.assert_allclose((ones(states) @ weights).numpy(), 1 / (1 - 0.95), rtol=1e-4)
    lookahead.improve(weights, 0.2)
    torch.testing.assert_close(lookahead.value_weights, 0.2 * weights)
    lookahead.restart()
    assert not lookahead.value_weights.any()


def test_a_known_termination_zeroes_the_value_past_it() -> None:
    reward = RewardSpec(lambda obs, a: torch.zeros(len(obs)), 1.0, lambda obs: obs[:, 0] > 0.5)
    next_obs, going_on, rewards = planner(1, reward).step(torch.zeros(1, 1), CANDIDATES)
    assert going_on.tolist() == [1.0, 1.0, 0.0] and rewards.tolist() == [0.0, 0.0, 1.0]  # the bonus where it ends
    np.testing.assert_allclose(next_obs[:, 0].numpy(), [-1.0, 0.0, 1.0], atol=1e-4)


def test_the_agent_plans_through_the_observation_model_with_discrete_actions_and_survives_save_load(tmp_path) -> None:
    kwargs = small_kwargs(
        policy_kwargs=CARTPOLE_POLICY,
        model_update={"kind": "observation", "holdout_size": 100},
        improvement={"method": "smoothed_greedy"},  # the preset's is soft
    )
    model = CMEPolicyIteration("CMEPolicy", "CartPole-v1", seed=0, tensorboard_log=str(tmp_path), **kwargs)
    model.learn(400, eval_env="CartPole-v1", eval_every=200, n_eval_episodes=2)
    lookahead = model.policy.lookahead
    assert lookahead.depth == 3 and model.q == 0  # two actions: 8 leaves; no psi is selected
    assert lookahead.value_weights.abs().sum() > 0 and lookahead.model.change.abs().sum() > 0
    model.save(tmp_path / "agent.zip")
    loaded = CMEPolicyIteration.load(tmp_path / "agent.zip")
    torch.testing.assert_close(loaded.policy.lookahead.value_weights, lookahead.value_weights)
    torch.testing.assert_close(loaded.policy.lookahead.model.change, lookahead.model.change)
    obs = np.random.default_rng(0).normal(0, 0.1, (32, 4)).astype(np.float32)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])


def test_by_default_the_lookahead_refines_its_first_action_where_the_reward_varies_and_the_cme_does_not() -> None:
    plain = {"preset": False, "verbose": 0}
    cme = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, model_update={"kind": "cme"}, **plain).policy
    observation = CMEPolicyIteration("CMEPolicy", "PointGoal2D-v0", seed=0, model_update={"kind": "observation"}, **plain)
    observation = observation.policy  # its reward is learned
    assert (cme.refine_steps, cme.refines) == (0, False)
    assert (observation.refine_steps, observation.refines) == (LOOKAHEAD_REFINE_STEPS, True)
    observation.lookahead.model.reward_range.fill_(1.0)  # a constant learned reward, as InvertedPendulum's
    assert (observation.refine_steps, observation.refines) == (0, False)


@pytest.mark.parametrize("refine_steps", [None, 0, 5])
def test_six_dim_actions_act_greedily_through_the_observation_model_and_survive_save_load(
    tmp_path, refine_steps: int | None
) -> None:
    kwargs = {
        **SMALL_BUDGETS,
        "model_update": {**SMALL_BUDGETS.get("model_update", {}), "kind": "observation"},
        "policy_kwargs": {"action_search": {"refine_steps": refine_steps}},
    }
    refines = refine_steps != 0  # None: the lookahead's default, LOOKAHEAD_REFINE_STEPS
    model = CMEPolicyIteration("CMEPolicy", PointMassSixActuators(), seed=0, **kwargs).learn(400)
    policy = model.policy
    assert policy.lookahead.depth == 1  # 257 candidates: 257^3 leaves is too many
    obs = np.random.default_rng(0).normal(0, 0.5, (16, 6)).astype(np.float32)
    actions = model.predict(obs, deterministic=True)[0]
    space = model.action_space
    assert actions.shape == (16, 6) and (actions >= space.low).all() and (actions <= space.high).all()
    candidates = {tuple(row) for row in policy.candidates.numpy().round(6)}
    assert any(tuple(row) not in candidates for row in actions.round(6)) == refines
    _, values = policy.greedy(torch.as_tensor(obs))
    best_candidate = policy.lookahead.greedy(policy.dynamics.phi, torch.as_tensor(obs), policy.candidates)[1]
    assert bool((values >= best_candidate).all()) and bool((values > best_candidate).any()) == refines
    model.save(tmp_path / "six.zip")
    np.testing.assert_array_equal(CMEPolicyIteration.load(tmp_path / "six.zip").predict(obs, deterministic=True)[0], actions)


@pytest.mark.parametrize("depth", [1, 2, 3])
def test_the_continuous_search_through_the_model_finds_a_known_maximiser_within_the_bounds(depth: int) -> None:
    # a known reward quadratic in a and a model that keeps s' = s: r(a*) is the best of every
    # step, so the first action's backed-up value r(a) + sum_k gamma^k g max_b r(b) peaks at a*
    low = np.array([-2.0, -1.0, 0.0, -0.5, -3.0, 1.0], np.float32)
    high = np.array([2.0, 1.0, 1.0, 0.5, 3.0, 2.0], np.float32)
    best = torch.tensor([0.7, -0.4, 0.25, 0.5, -1.0, 1.6])  # the fourth on its upper bound
    curvature = torch.tensor([1.0, 3.0, 10.0, 1.0, 0.3, 5.0])
    reward = RewardSpec(lambda obs, a: -(((a - best) ** 2) * curvature).sum(dim=1), 0.0, lambda obs: obs[:, 0] > 100)
    policy = CMEPolicy(
        spaces.Box(-1.0, 1.0, (2,), np.float32),
        spaces.Box(low, high),
        phi={"resolution": [5]},
        reward=reward,
        action_search={"n_samples": 64, "refine_steps": 80, "lookahead_depth": depth},
        model_kind="observation",
    )
    obs = torch.rand(5, 2) * 2 - 1
    actions, values = policy.greedy(obs)
    assert bool((actions >= torch.as_tensor(low)).all() and (actions <= torch.as_tensor(high)).all())
    assert (actions - best).abs().max() < 0.03
    candidates = policy.candidates
    best_candidate = float(reward.step_reward(torch.zeros(len(candidates), 2), candidates).max())
    later = sum(0.95**k for k in range(1, depth)) * best_candidate
    torch.testing.assert_close(values, reward.step_reward(obs, actions) + later, atol=1e-4, rtol=0)
    np.testing.assert_allclose(policy.predict(obs.numpy(), deterministic=True)[0], actions.numpy(), atol=1e-6)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (
            {"policy_kwargs": {"action_search": {"lookahead_depth": 3}}},
            r"lookahead_depth=3 is invalid with model_update.kind='cme'",
        ),
        (
            {"model_update": {"kind": "observation"}, "improvement": {"method": "soft"}},
            r"improvement.method='soft' is invalid",
        ),
        ({"model_update": {"kind": "next_state"}}, r"model_update.kind"),
        (
            {"model_update": {"kind": "observation"}, "policy_kwargs": {"action_search": {"lookahead_depth": 5}}},
            r"lookahead_depth=5 is invalid with 21 candidate actions: 21\^5 leaves",  # Pendulum's preset: 21 torques
        ),
        ({"policy_kwargs": {"action_search": {"lookahead_depth": 0}}}, r"lookahead_depth"),
    ],
)
def test_settings_the_lookahead_cannot_honour_are_refused_by_name(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **kwargs)


def test_the_dashboards_show_the_lookahead_and_the_error_of_its_model() -> None:
    kwargs = small_kwargs(model_update={"kind": "observation", "holdout_size": 100}, policy_kwargs=PENDULUM_POLICY)
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **kwargs).learn(300)
    pictures = agent_pictures(model, resolution=8)
    assert set(pictures) == set(PICTURE_TAGS) - {"pictures/feature_centres"}  # no psi
    obs, errors = holdout_errors(model)
    assert len(errors) > 0 and len(obs) == len(errors) and (errors >= 0).all()
    policy, state = model.policy, torch.tensor([[1.0, 0.0, 0.0]])
    _, values = policy.greedy(state.expand(4, 3))
    expected = policy.lookahead.backed_up_paths(model.dynamics.phi, state, policy.candidates, policy.lookahead.depth - 1)[0]
    torch.testing.assert_close(values, expected.max(dim=1).values.expand(4))


def test_eq7_compares_a_fresh_draw_of_candidates_when_the_pairs_would_not_fit(monkeypatch) -> None:
    lookahead, seen = planner(1, RewardSpec(lambda obs, a: -(a[:, 0] ** 2))), []
    step = lookahead.step
    monkeypatch.setattr(lookahead, "step", lambda obs, candidates: seen.append(candidates) or step(obs, candidates))
    monkeypatch.setattr("cme_agent.lookahead.PLANNING_PAIRS", 600)
    many, states, generator = torch.linspace(-1, 1, 21).unsqueeze(1), torch.zeros(200, 1), torch.Generator().manual_seed(0)
    for _ in range(2):
        lookahead.evaluate(ones, states, many, 1e-6, Logger(None, []), generator)
    assert [len(drawn) for drawn in seen] == [3, 3] and not torch.equal(seen[0], seen[1])  # 600 // 200 per round, redrawn
    assert all(((drawn >= -1) & (drawn <= 1)).all() and len(drawn.unique()) == 3 for drawn in seen)
