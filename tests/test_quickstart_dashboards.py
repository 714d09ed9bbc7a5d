"""The Python quickstart gets train.py's dashboards: with tensorboard_log= and learn(eval_env=...),
eval/ curves at several steps, the returns by behaviour and the pictures; the same agent as
without them; the evaluation env's starts the same at every evaluation."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from cme_agent import CMEPolicyIteration
from cme_agent.callbacks import EpisodeReturnsByBehaviour, PeriodicEvaluation
from cme_agent.dashboards import Dashboards, evaluation_env_factory, with_dashboards
from cme_agent.pictures import PICTURE_TAGS, PictureCallback


def _events(folder) -> EventAccumulator:
    (run,) = [path for path in folder.iterdir() if path.is_dir()]  # tensorboard_log/<tb_log_name>_1
    events = EventAccumulator(str(run), size_guidance={"images": 0, "scalars": 0})
    events.Reload()
    return events


def test_the_quickstart_with_eval_env_has_train_pys_dashboards(tmp_path, pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, tensorboard_log=str(tmp_path), **pendulum_kwargs)
    model.learn(total_timesteps=500, eval_env="Pendulum-v1", eval_every=200, n_eval_episodes=1)
    events = _events(tmp_path)
    scalars = events.Tags()["scalars"]
    # every 200 steps at iteration boundaries, and the final policy
    assert [event.step for event in events.Scalars("eval/mean_reward")] == [200, 400, 500]
    assert "rollout/greedy_ep_rew_mean" in scalars or "rollout/explore_ep_rew_mean" in scalars
    assert set(PICTURE_TAGS) <= set(events.Tags()["images"])
    assert events.Images("pictures/value")


def test_without_eval_env_the_pictures_and_returns_by_behaviour_still_come(tmp_path, pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, tensorboard_log=str(tmp_path), **pendulum_kwargs)
    model.learn(400)
    events = _events(tmp_path)
    assert "eval/mean_reward" not in events.Tags()["scalars"]
    assert set(PICTURE_TAGS) <= set(events.Tags()["images"])


def test_the_dashboards_do_not_change_the_agent(pendulum_kwargs):
    plain = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=3, **pendulum_kwargs)
    plain.learn(300)
    watched = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=3, **pendulum_kwargs)
    watched.learn(300, eval_env="Pendulum-v1", eval_every=100, n_eval_episodes=1)
    assert torch.equal(watched.dynamics.weights, plain.dynamics.weights)
    assert torch.equal(watched.policy.theta_phi, plain.policy.theta_phi)


def _first_starts(make_env) -> list[np.ndarray]:
    """The first observation of two evaluations (evaluate_policy resets a VecEnv of the env)."""
    starts = []
    for _ in range(2):
        env = make_env()
        vec_env = env if hasattr(env, "num_envs") else DummyVecEnv([lambda env=env: env])
        starts.append(vec_env.reset()[0])
    return starts


@pytest.mark.parametrize(
    "eval_env",
    [lambda: "Pendulum-v1", lambda: gym.make("Pendulum-v1"), lambda: make_vec_env("Pendulum-v1", n_envs=1)],
    ids=["id", "env", "vec_env"],
)
def test_every_evaluation_flies_the_same_starts(eval_env):
    make_env, _ = evaluation_env_factory(eval_env(), seed=10_003)
    first, again = _first_starts(make_env)
    np.testing.assert_array_equal(first, again)
    other, _ = evaluation_env_factory(eval_env(), seed=10_004)
    assert not np.array_equal(_first_starts(other)[0], first)


def test_a_users_own_callbacks_of_those_kinds_replace_the_defaults(pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    mine = [EpisodeReturnsByBehaviour(), PictureCallback(every=3)]
    callbacks, sb3_bar = with_dashboards(model, mine, "Pendulum-v1", 100, 1, progress_bar=True)
    dashboards = callbacks[0]
    assert isinstance(dashboards, Dashboards) and callbacks[1:] == mine and not sb3_bar
    kinds = [type(callback).__name__ for callback in dashboards.callbacks]
    assert kinds == ["PeriodicEvaluation", "EvaluationProgressBar"]
    # train.py's own Dashboards is used as it is, and eval_env beside it is refused
    assert with_dashboards(model, [dashboards], None, 100, 1, progress_bar=False) == ([dashboards], False)
    with pytest.raises(ValueError, match="eval_env"):
        with_dashboards(model, [dashboards], "Pendulum-v1", 100, 1, progress_bar=False)


def test_a_stopped_learn_does_not_evaluate_the_final_policy(pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    evaluation = PeriodicEvaluation(lambda: Monitor(gym.make("Pendulum-v1")), eval_every=0, n_eval_episodes=1)
    stop_early = Dashboards(evaluation, [])
    model.learn(300, callback=[stop_early, lambda _locals, _globals: model.num_timesteps < 150])
    assert model.num_timesteps == 150 and evaluation.evaluations == []
    model.learn(200, callback=stop_early)
    assert [item.timesteps for item in evaluation.evaluations] == [200]
