"""The SB3 callback contract: on_step once per env step, False stops learn(); SB3's own
callbacks and vectorised envs work."""

import numpy as np
from stable_baselines3.common.callbacks import (
    CheckpointCallback,
    EvalCallback,
    StopTrainingOnMaxEpisodes,
)
from stable_baselines3.common.env_util import make_vec_env

from cme_agent import CMEPolicyIteration
from tests.conftest import CountingCallback


def test_on_step_once_per_env_step(pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    callback = CountingCallback()
    model.learn(300, callback=callback)
    assert callback.calls == model.num_timesteps == 300


def test_callback_returning_false_stops_learning(pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    callback = CountingCallback(stop_after=150)
    model.learn(1000, callback=callback)
    assert callback.calls == 150
    assert model.num_timesteps == 150
    assert model.iteration == 1  # the second iteration was cut off mid-acquisition
    assert len(model.store) + len(model.holdout) == 150  # its data is kept


def test_vec_env_with_several_envs(pendulum_kwargs):
    env = make_vec_env("Pendulum-v1", n_envs=3, seed=0)
    model = CMEPolicyIteration("CMEPolicy", env, seed=0, **pendulum_kwargs)
    callback = CountingCallback()
    model.learn(600, callback=callback)
    assert callback.calls == 200  # one call per vector step
    assert model.num_timesteps == 600
    assert len(model.store) + len(model.holdout) == 600
    assert model.iteration == 6  # ceil(100 / 3) vector steps per iteration


def test_sb3_callbacks(tmp_path, cartpole_kwargs):
    env = make_vec_env("CartPole-v1", n_envs=1, seed=0)
    eval_env = make_vec_env("CartPole-v1", n_envs=1, seed=1)
    model = CMEPolicyIteration("CMEPolicy", env, seed=0, **cartpole_kwargs)
    eval_callback = EvalCallback(eval_env, n_eval_episodes=2, eval_freq=100, log_path=str(tmp_path), verbose=0)
    checkpoint = CheckpointCallback(save_freq=150, save_path=str(tmp_path / "ckpt"), name_prefix="cme")
    model.learn(200, callback=[eval_callback, checkpoint])
    q_after_two_iterations = model.q
    model.learn(100, callback=[eval_callback, checkpoint], reset_num_timesteps=False)
    assert np.load(tmp_path / "evaluations.npz")["results"].shape[1] == 2
    assert sorted(p.name for p in (tmp_path / "ckpt").iterdir()) == ["cme_150_steps.zip", "cme_300_steps.zip"]
    # the step-300 checkpoint is taken during iteration 3's acquisition, before its planning
    loaded = CMEPolicyIteration.load(tmp_path / "ckpt" / "cme_300_steps.zip")
    assert loaded.q == q_after_two_iterations
    assert loaded.num_timesteps == 300
    assert int(loaded.predict(eval_env.reset())[0][0]) in (0, 1)


def test_stop_on_max_episodes(pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    model.learn(5000, callback=StopTrainingOnMaxEpisodes(max_episodes=2))
    assert model.num_timesteps == 400  # two 200-step episodes


def test_set_env_and_continue(pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    model.learn(200)
    new_env = make_vec_env("Pendulum-v1", n_envs=1, seed=5)
    model.set_env(new_env)
    model.learn(200, reset_num_timesteps=False)
    assert model.get_env() is new_env
    assert model.num_timesteps == 400 and len(model.store) + len(model.holdout) == 400


def test_progress_bar(pendulum_kwargs):
    """SB3's ProgressBarCallback reads learn()'s local total_timesteps; it needs tqdm and rich installed."""
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    model.learn(200, progress_bar=True)
    assert model.num_timesteps == 200
