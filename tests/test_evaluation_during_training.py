"""Evaluation during training: scalars at several steps, greedy and exploratory returns apart,
and an agent trained with them equal to one trained without."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3.common.logger import configure
from stable_baselines3.common.monitor import Monitor
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from cme_agent import CMEPolicyIteration
from cme_agent.callbacks import EpisodeReturnsByBehaviour, PeriodicEvaluation


def _eval_env() -> gym.Env:
    env = Monitor(gym.make("Pendulum-v1"))
    env.reset(seed=10_000)
    return env


def _scalars(folder) -> dict[str, list[tuple[int, float]]]:
    events = EventAccumulator(str(folder))
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def test_eval_scalars_at_several_steps_and_returns_by_behaviour(tmp_path, pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    model.set_logger(configure(str(tmp_path), ["tensorboard"]))
    evaluation = PeriodicEvaluation(_eval_env, eval_every=200, n_eval_episodes=1, log_path=tmp_path / "evaluations.npz")
    model.learn(1000, callback=[evaluation, EpisodeReturnsByBehaviour()])
    evaluation.evaluate()  # the final policy
    scalars = _scalars(tmp_path)
    for key in ("eval/mean_reward", "eval/std_reward", "eval/mean_ep_length"):
        assert [step for step, _ in scalars[key]] == [200, 400, 600, 800, 1000], key
    assert [value for _, value in scalars["eval/mean_ep_length"]] == [200.0] * 5
    saved = np.load(tmp_path / "evaluations.npz")  # SB3's EvalCallback format
    assert saved["timesteps"].tolist() == [200, 400, 600, 800, 1000] and saved["results"].shape == (5, 1)
    np.testing.assert_allclose(saved["results"][:, 0], [value for _, value in scalars["eval/mean_reward"]], rtol=1e-6)
    # 5 training episodes of 200 steps; the first lies in the random phase (100 steps), the others
    # end at iterations 4, 6, 8, 10 and are logged there, each under its kind
    by_kind = {k: scalars.get(f"rollout/{k}_ep_rew_mean", []) for k in ("greedy", "explore")}
    assert sorted(step for points in by_kind.values() for step, _ in points) == [400, 600, 800, 1000]
    logged = sorted(value for points in by_kind.values() for _, value in points)
    np.testing.assert_allclose(logged, sorted(info["r"] for info in list(model.ep_info_buffer)[1:]), rtol=1e-5)


def test_evaluation_does_not_change_training(pendulum_kwargs):
    plain = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=3, **pendulum_kwargs)
    plain.learn(400)
    watched = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=3, **pendulum_kwargs)
    watched.learn(
        400, callback=[PeriodicEvaluation(_eval_env, eval_every=100, n_eval_episodes=1), EpisodeReturnsByBehaviour()]
    )
    assert torch.equal(watched.dynamics.weights, plain.dynamics.weights)
    for name in ("theta_psi", "theta_phi"):
        assert torch.equal(getattr(watched.policy, name), getattr(plain.policy, name)), name


def test_evaluations_resume_up_to_the_checkpoint(tmp_path, pendulum_kwargs):
    """A second learn() from step 300 keeps the file's evaluations up to 300, drops the later ones."""
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    log_path = tmp_path / "evaluations.npz"
    model.learn(500, callback=PeriodicEvaluation(_eval_env, eval_every=100, n_eval_episodes=1, log_path=log_path))
    assert np.load(log_path)["timesteps"].tolist() == [100, 200, 300, 400]
    model.num_timesteps = 300  # as a model loaded from a checkpoint taken at step 300
    again = PeriodicEvaluation(_eval_env, eval_every=100, n_eval_episodes=1, log_path=log_path)
    model.learn(100, callback=again, reset_num_timesteps=False)
    assert [e.timesteps for e in again.evaluations] == [100, 200, 300]


@pytest.mark.parametrize("bad", [{"eval_every": -1}, {"eval_every": 10, "n_eval_episodes": 0}])
def test_bad_evaluation_settings_are_refused(bad):
    with pytest.raises(ValueError, match="invalid"):
        PeriodicEvaluation(_eval_env, **bad)
