"""Tests of ToyChain-v0, the paper's Toy MDP: the env, its config, and learning it."""

import inspect
import warnings
from collections.abc import Iterator
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import stable_baselines3.common.env_checker as sb3_env_checker
import torch
import yaml
from gymnasium.utils import env_checker as gym_env_checker
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import cme_agent.envs  # noqa: F401  (registers ToyChain-v0)
from cme_agent.envs.toy_chain import ToyChainEnv
from cme_agent.experiment import build_agent, evaluate, make_env

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "conf" / "env" / "toy.yaml"


def rollout(env: ToyChainEnv, seed: int, actions: np.ndarray) -> tuple[np.ndarray, list[float]]:
    """Observations ``(T + 1, 1)`` and rewards of a fixed action sequence from ``reset(seed)``."""
    observations, rewards = [env.reset(seed=seed)[0]], []
    for action in actions:
        obs, reward, *_ = env.step(action)
        observations.append(obs)
        rewards.append(reward)
    return np.array(observations), rewards


def random_actions(env: ToyChainEnv, steps: int, seed: int = 0) -> np.ndarray:
    """``steps`` actions of the env's kind: Box ``(steps, 1)`` float32 or Discrete ``(steps,)``."""
    rng = np.random.default_rng(seed)
    if env.discrete_actions:
        return rng.integers(3, size=steps)
    return rng.uniform(-1.0, 1.0, (steps, 1)).astype(np.float32)


# --- the environment -------------------------------------------------------------------------


@pytest.mark.parametrize("discrete_actions", [False, True])
@pytest.mark.parametrize("render_mode", [None, "rgb_array"])
def test_env_checkers_pass_without_warnings(discrete_actions: bool, render_mode: str | None) -> None:
    for check in (gym_env_checker.check_env, sb3_env_checker.check_env):
        env = gym.make("ToyChain-v0", discrete_actions=discrete_actions, render_mode=render_mode)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            check(env.unwrapped)
        assert not caught, [str(w.message) for w in caught]


def test_make_with_yaml_kwargs() -> None:
    kwargs = yaml.safe_load(CONFIG.read_text())["env"]["kwargs"]
    assert set(kwargs) == set(inspect.signature(ToyChainEnv).parameters), "conf/env/toy.yaml must list every argument"
    env = gym.make("ToyChain-v0", **kwargs)
    assert env.spec.max_episode_steps is None, "the env truncates by itself"
    assert env.unwrapped.goal == kwargs["goal"] and env.unwrapped.max_steps == kwargs["max_steps"]


@pytest.mark.parametrize("discrete_actions", [False, True])
def test_noiseless_transition_follows_the_documented_law(discrete_actions: bool) -> None:
    """x' = clip(x + step_size * a, -1, 1) in float32, with a Box action clipped to [-1, 1]
    and Discrete actions 0, 1, 2 meaning -1, 0, +1."""
    env = ToyChainEnv(noise_std=0.0, step_size=0.3, start_low=-1.0, start_high=1.0, discrete_actions=discrete_actions)
    actions = random_actions(env, 200)
    if not discrete_actions:
        actions = (1.5 * actions).astype(np.float32)  # some outside [-1, 1]
    observations, _ = rollout(env, 0, actions)
    direction = actions - 1.0 if discrete_actions else np.clip(actions[:, 0].astype(np.float64), -1.0, 1.0)
    expected = np.clip(observations[:-1, 0].astype(np.float64) + 0.3 * direction, -1.0, 1.0).astype(np.float32)
    np.testing.assert_array_equal(observations[1:, 0], expected)
    assert np.sum(np.abs(observations[1:, 0]) == 1.0) > 5, "the walk should hit the ends of the interval"


def test_transition_noise_has_the_documented_std() -> None:
    """One step of action 0 from x = 0, repeated: x' is the noise alone."""
    env = ToyChainEnv(noise_std=0.05, start_low=0.0, start_high=0.0)
    env.reset(seed=0)
    increments = []
    for _ in range(2000):
        increments.append(env.step(np.zeros(1, dtype=np.float32))[0][0])
        env.reset()
    assert np.mean(increments) == pytest.approx(0.0, abs=0.005)
    assert np.std(increments) == pytest.approx(0.05, rel=0.05)


@pytest.mark.parametrize("discrete_actions", [False, True])
def test_reward_is_reward_function_of_the_state_before_the_step(discrete_actions: bool) -> None:
    env = ToyChainEnv(start_low=0.2, start_high=0.6, discrete_actions=discrete_actions)
    actions = random_actions(env, 50)
    observations, rewards = rollout(env, 1, actions)
    expected = env.reward_function(torch.as_tensor(observations[:-1]), torch.as_tensor(actions))
    assert expected.shape == (50,) and expected.dtype == torch.float32
    assert torch.equal(torch.tensor(rewards, dtype=torch.float32), expected)
    bump = np.exp(-((observations[:-1, 0] - env.goal) ** 2) / (2.0 * env.sigma**2))
    np.testing.assert_allclose(rewards, bump, rtol=1e-6)
    assert max(rewards) > 0.5, "the rollout should pass near the goal"


def test_episode_is_truncated_after_max_steps_and_never_terminated() -> None:
    env = ToyChainEnv(max_steps=7, goal=-0.7, start_low=-0.7, start_high=-0.7)
    env.reset(seed=0)
    flags = []
    for _ in range(7):
        _, reward, terminated, truncated, _ = env.step(np.zeros(1, dtype=np.float32))
        assert type(reward) is float and type(terminated) is bool and type(truncated) is bool
        flags.append((terminated, truncated))
    assert flags == [(False, False)] * 6 + [(False, True)], "sitting on the goal must not end the episode"
    assert not env.termination_function(torch.linspace(-1.0, 1.0, 11)[:, None]).any()


def test_seeding_is_deterministic() -> None:
    env = ToyChainEnv()
    actions = random_actions(env, 30)
    first, second = rollout(env, 7, actions)[0], rollout(ToyChainEnv(), 7, actions)[0]
    np.testing.assert_array_equal(first, second)
    other = rollout(env, 8, actions)[0]
    assert not np.array_equal(first, other)
    starts = np.array([env.reset(seed=seed)[0][0] for seed in range(50)])
    assert starts.min() >= env.start_low and starts.max() <= env.start_high and starts.std() > 0.05


def test_observations_are_fresh_arrays() -> None:
    env = ToyChainEnv(noise_std=0.0)
    obs, _ = env.reset(seed=0)
    start = float(obs[0])
    next_obs, *_ = env.step(np.ones(1, dtype=np.float32))
    assert next_obs is not obs
    obs[:] = 0.9
    next_obs[:] = 0.9
    third, *_ = env.step(np.ones(1, dtype=np.float32))
    assert third[0] == pytest.approx(start + 0.2, abs=1e-6), "mutating a returned observation must not change the env"


@pytest.mark.parametrize(
    ("argument", "value"),
    [
        ("goal", 1.5),
        ("goal", float("nan")),
        ("sigma", 0.0),
        ("start_low", -2.0),
        ("start_high", -0.95),  # below the default start_low
        ("step_size", 0.0),
        ("step_size", 3.0),
        ("noise_std", -0.1),
        ("max_steps", 0),
        ("max_steps", 2.5),
        ("discrete_actions", "yes"),
        ("render_mode", "human"),
        ("render_size", 10),
    ],
)
def test_bad_arguments_raise(argument: str, value: object) -> None:
    with pytest.raises(ValueError, match=argument):
        ToyChainEnv(**{argument: value})


def test_rgb_array_render_shows_the_agent_moving() -> None:
    env = ToyChainEnv(render_mode="rgb_array", render_size=120, noise_std=0.0)
    env.reset(seed=0)
    first = env.render()
    assert first.dtype == np.uint8 and first.shape == (60, 120, 3)
    for _ in range(5):
        env.step(np.ones(1, dtype=np.float32))
    second = env.render()
    assert np.count_nonzero(np.any(first != second, axis=2)) > 20
    assert env.metadata["render_fps"] > 0


# --- learning it -----------------------------------------------------------------------------


@pytest.fixture
def one_torch_thread() -> Iterator[None]:
    """Small matrices gain nothing from threads, and on a busy machine they cost a lot."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def random_policy_return(env_kwargs: dict, episodes: int, seed: int) -> float:
    """Mean return of uniformly random actions over ``episodes`` episodes."""
    env = ToyChainEnv(**env_kwargs)
    env.action_space.seed(seed)
    returns = []
    for episode in range(episodes):
        env.reset(seed=seed + episode)
        total, truncated = 0.0, False
        while not truncated:
            _, reward, _, truncated, _ = env.step(env.action_space.sample())
            total += reward
        returns.append(total)
    return float(np.mean(returns))


def test_cme_agent_learns_the_toy_chain_from_the_hydra_config(one_torch_thread: None) -> None:
    """``env=toy`` composes (with the env's preset) into an agent that reaches and
    holds the goal after the config's budget (3000 steps, ~5 s): its return beats a random
    policy's by half of ``max_steps`` (the best return is ~0.8 of it); the same agent
    untrained does not, so the bar is cleared by learning alone."""
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose(config_name="config", overrides=["env=toy", "verbose=0", "eval_episodes=5"])
    env = make_env(cfg)
    agent = build_agent(cfg, env)
    bar = random_policy_return(OmegaConf.to_container(cfg.env.kwargs), episodes=20, seed=0) + 0.5 * cfg.env.kwargs.max_steps
    untrained_return = evaluate(agent, cfg)[0]
    agent.learn(cfg.total_timesteps)
    trained_return = evaluate(agent, cfg)[0]
    assert agent.reward_source == "env"
    assert untrained_return < bar < trained_return
    env.close()
