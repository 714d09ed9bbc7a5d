"""``improvement.deploy="best_return"``: predict() acts with the policy whose greedy training
episodes returned the most, data acquisition with the last one, and the choice survives save/load."""

import copy

import numpy as np
import pytest
import torch
from gymnasium import spaces

from cme_agent import CMEPolicyIteration
from cme_agent.callbacks import EpisodeReturnsByBehaviour
from cme_agent.config import ExplorationConfig, ImprovementConfig
from cme_agent.exploration import BehaviourPolicy

BEST = {"deploy": "best_return"}


class DeploymentHistory(EpisodeReturnsByBehaviour):
    """Per acquisition: the greedy episodes' returns as Monitor reports them, and the deployed
    policy after the agent's choice (which the agent makes before ``on_rollout_end``)."""

    def __init__(self) -> None:
        super().__init__()
        self.history: list[tuple[list[float], float, int, int]] = []

    def _on_rollout_end(self) -> None:
        policy = self.model.policy
        greedy = list(self._returns["greedy"])
        self.history.append((greedy, float(policy.deployed_return), int(policy.deployed_iteration), self.model.iteration))
        super()._on_rollout_end()


def _observations(n=64, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.uniform(-1, 1, size=(n, 4)) * np.array([2.0, 2.0, 0.2, 2.0])).astype(np.float32)


def test_greedy_returns_count_only_whole_greedy_episodes():
    config = ExplorationConfig(explore_fraction=0.0)
    behaviour = BehaviourPolicy(spaces.Discrete(2), config, np.random.default_rng(0), n_envs=2)
    none, done_first = np.zeros(2, dtype=bool), np.array([True, False])
    behaviour(lambda: np.zeros(2), random_phase=True)
    assert behaviour.greedy_returns(np.array([1.0, 1.0]), done_first).size == 0  # a random step: not greedy
    behaviour.end_episodes(done_first)
    behaviour(lambda: np.zeros(2), random_phase=False)
    assert behaviour.greedy_returns(np.array([2.0, 5.0]), none).size == 0
    behaviour(lambda: np.zeros(2), random_phase=False)
    assert behaviour.greedy_returns(np.array([3.0, 5.0]), np.array([True, True])).tolist() == [5.0]  # env 1 had random steps
    behaviour.end_episodes(np.array([True, True]))
    behaviour.explore[1] = True  # an exploratory episode
    behaviour(lambda: np.zeros(2), random_phase=False)
    assert behaviour.greedy_returns(np.array([-1.0, 7.0]), np.array([True, True])).tolist() == [-1.0]


def test_deploy_is_checked():
    with pytest.raises(ValueError, match=r"improvement.deploy='best' is invalid"):
        ImprovementConfig(deploy="best")
    with pytest.raises(ValueError, match=r"improvement.deploy_min_episodes=0 is invalid"):
        ImprovementConfig(deploy_min_episodes=0)


@pytest.fixture(scope="module")
def trained():
    """The same CartPole run with ``deploy="best_return"`` (and its deployment history) and with ``"last"``."""
    from tests.conftest import CARTPOLE_POLICY, small_kwargs

    kwargs = small_kwargs(policy_kwargs=CARTPOLE_POLICY)
    best = CMEPolicyIteration("CMEPolicy", "CartPole-v1", seed=1, improvement=BEST, **kwargs)
    history = DeploymentHistory()
    best.learn(1500, callback=history)
    last = CMEPolicyIteration("CMEPolicy", "CartPole-v1", seed=1, **kwargs)
    last.learn(1500, callback=DeploymentHistory())
    return best, history.history, last


def test_the_deployed_policy_is_the_best_greedy_return_so_far(trained):
    """Against Monitor's returns, logged independently: after each acquisition the deployed
    policy's return is the best mean so far, and its iteration the newest that had it."""
    model, history, _ = trained
    best, best_iteration = -np.inf, -1
    for greedy, deployed_return, deployed_iteration, iteration in history:
        if greedy and iteration > 0 and np.mean(greedy) >= best:
            best, best_iteration = float(np.mean(greedy)), iteration
        assert deployed_return == pytest.approx(best) and deployed_iteration == best_iteration
    assert 0 < best_iteration < model.iteration  # the test needs a deployed policy other than the last
    obs = _observations()
    last = copy.deepcopy(model.policy)
    last.improvement = ImprovementConfig()
    deployed = copy.deepcopy(last)
    deployed.theta_phi, deployed.theta_psi = model.policy.deployed_phi.clone(), model.policy.deployed_psi.clone()
    assert (model.predict(obs, deterministic=True)[0] == deployed.predict(obs, deterministic=True)[0]).all()
    assert (model.policy.last_policy_actions(obs) == last.predict(obs, deterministic=True)[0]).all()
    assert (model.predict(obs)[0] != model.policy.last_policy_actions(obs)).any()


def test_learning_is_the_same_whatever_is_deployed(trained):
    """Data acquisition acts with the last policy either way: the runs take the same steps and
    end with the same Q; with ``"last"`` nothing is deployed and predict() acts with the last policy."""
    best, _, last = trained
    assert best.q == last.q and best.policy.theta_psi.shape == last.policy.theta_psi.shape
    assert np.array_equal(best.policy.theta_psi.numpy(), last.policy.theta_psi.numpy())
    obs = _observations()
    assert float(last.policy.deployed_return) == -np.inf and not last.policy.deploys_selected
    assert (last.predict(obs)[0] == last.policy.last_policy_actions(obs)).all()


def test_the_deployed_policy_survives_save_load_and_restart(trained, tmp_path):
    model = copy.deepcopy(trained[0])
    model.save(tmp_path / "agent")
    loaded = CMEPolicyIteration.load(tmp_path / "agent")
    obs = _observations()
    assert loaded.policy.deploys_selected
    assert int(loaded.policy.deployed_iteration) == int(model.policy.deployed_iteration)
    assert (loaded.predict(obs)[0] == model.predict(obs)[0]).all()
    assert (loaded.policy.last_policy_actions(obs) == model.policy.last_policy_actions(obs)).all()
    state = {k: v for k, v in model.policy.state_dict().items() if not k.startswith("deployed_")}
    loaded.policy.load_state_dict(state)  # a file written before deployment: the last policy acts
    assert not loaded.policy.deploys_selected and (loaded.predict(obs)[0] == model.policy.last_policy_actions(obs)).all()
    model.policy.restart()
    assert not model.policy.deploys_selected and model.policy.deployed_psi.numel() == 0


def test_consider_for_deployment_rules(trained):
    """At least deploy_min_episodes episodes; a lower mean is not deployed; a tie goes to the newer policy."""
    policy = copy.deepcopy(trained[0].policy)
    policy.improvement = ImprovementConfig(deploy="best_return", deploy_min_episodes=2)
    policy.restart()
    policy.theta_psi = torch.ones(3)
    assert not policy.consider_for_deployment([100.0], iteration=3)  # one episode of the two needed
    assert policy.consider_for_deployment([8.0, 12.0], iteration=3) and int(policy.deployed_iteration) == 3
    policy.theta_psi = torch.full((4,), 2.0)
    assert not policy.consider_for_deployment([9.0, 10.0], iteration=4)
    assert policy.deployed_psi.tolist() == [1.0, 1.0, 1.0]
    assert policy.consider_for_deployment([10.0, 10.0], iteration=5)
    assert int(policy.deployed_iteration) == 5 and policy.deployed_psi.tolist() == [2.0] * 4
    policy.theta_psi.fill_(7.0)  # the deployed weights are a copy
    assert policy.deployed_psi.tolist() == [2.0] * 4
    policy.improvement = ImprovementConfig()
    assert not policy.consider_for_deployment([1e9, 1e9], iteration=6) and int(policy.deployed_iteration) == 5
