"""The behaviour policy: mixing, temporally extended random actions, AR(1) noise."""

import numpy as np
from gymnasium import spaces

from cme_agent.config import ExplorationConfig
from cme_agent.exploration import BehaviourPolicy


def _greedy(n, value=0):
    return lambda: np.full(n, value)


def test_random_phase_holds_each_action_for_repeat_steps():
    behaviour = BehaviourPolicy(spaces.Discrete(5), ExplorationConfig(repeat=4), np.random.default_rng(0), n_envs=3)
    actions = np.stack([behaviour(_greedy(3), random_phase=True) for _ in range(12)])
    for block in range(3):
        rows = actions[4 * block : 4 * block + 4]
        assert (rows == rows[0]).all()
    assert len({tuple(actions[4 * b]) for b in range(3)}) > 1  # a new draw after each hold


def test_greedy_outside_exploratory_episodes():
    config = ExplorationConfig(explore_fraction=0.0, epsilon=1.0, noise_std=1.0)
    discrete = BehaviourPolicy(spaces.Discrete(3), config, np.random.default_rng(0), n_envs=4)
    assert (discrete(_greedy(4, 2), random_phase=False) == 2).all()
    box = spaces.Box(-1.0, 1.0, (2,), np.float32)
    continuous = BehaviourPolicy(box, config, np.random.default_rng(0), n_envs=4)
    assert (continuous(lambda: np.full((4, 2), 0.5, np.float32), random_phase=False) == 0.5).all()


def test_epsilon_random_actions_in_exploratory_episodes():
    config = ExplorationConfig(explore_fraction=1.0, epsilon=0.5)
    behaviour = BehaviourPolicy(spaces.Discrete(10), config, np.random.default_rng(0), n_envs=1000)
    actions = behaviour(_greedy(1000, 0), random_phase=False)
    share_random = np.mean(actions != 0)
    assert 0.4 < share_random < 0.5  # half are random, a tenth of those pick 0 again


def test_box_noise_has_the_marginal_std_and_the_correlation_time():
    box = spaces.Box(-100.0, 100.0, (1,), np.float32)
    config = ExplorationConfig(explore_fraction=1.0, noise_std=0.01, repeat=10)  # std 1 in env units
    behaviour = BehaviourPolicy(box, config, np.random.default_rng(0), n_envs=2000)
    series = np.stack([behaviour(lambda: np.zeros((2000, 1), np.float32), random_phase=False)[:, 0] for _ in range(60)])
    settled = series[30:]
    assert abs(settled.std() - 1.0) < 0.05
    lag_one = np.mean(settled[1:] * settled[:-1]) / settled.var()
    assert abs(lag_one - 0.9) < 0.03


def test_episode_end_redraws_and_clears():
    config = ExplorationConfig(explore_fraction=0.5, repeat=5)
    behaviour = BehaviourPolicy(spaces.Discrete(3), config, np.random.default_rng(0), n_envs=200)
    behaviour(_greedy(200), random_phase=True)
    before = behaviour.explore.copy()
    done = np.zeros(200, dtype=bool)
    done[:100] = True
    behaviour.end_episodes(done)
    assert (behaviour.hold_left[:100] == 0).all() and (behaviour.hold_left[100:] == 4).all()
    assert (behaviour.explore[100:] == before[100:]).all()
    assert (behaviour.explore[:100] != before[:100]).any()
