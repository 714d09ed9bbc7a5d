"""torch's thread count during learn(): the agent's n_threads (default 1) in the Python API and in
train.py alike, a user's explicit value winning, the caller's setting put back afterwards."""

from __future__ import annotations

import pytest
import torch
from hydra import compose, initialize_config_dir
from stable_baselines3.common.callbacks import BaseCallback

import cme_agent.experiment
from cme_agent import CMEPolicyIteration
from cme_agent.dashboards import training_dashboards
from cme_agent.experiment import run
from cme_agent.threads import DEFAULT_THREADS
from tests.conftest import ROOT


class ThreadProbe(BaseCallback):
    """Records ``torch.get_num_threads()`` at every env step and at the end of training."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: set[int] = set()

    def _on_step(self) -> bool:
        self.seen.add(torch.get_num_threads())
        return True

    def _on_training_end(self) -> None:
        self.seen.add(torch.get_num_threads())


@pytest.fixture
def caller_threads():
    """The test's own setting (2, not the default 1), put back after the test."""
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield 2
    torch.set_num_threads(before)


@pytest.mark.parametrize(
    ("n_threads", "caller", "inside"),
    [(DEFAULT_THREADS, 2, 1), (2, 1, 2), (None, 2, 2)],  # the default, a user's explicit value, torch's own setting
)
def test_learn_runs_at_the_agents_thread_count_and_puts_the_callers_back(
    pendulum_kwargs, caller_threads, n_threads, caller, inside
):
    torch.set_num_threads(caller)
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, n_threads=n_threads, **pendulum_kwargs)
    probe = ThreadProbe()
    model.learn(200, callback=probe)
    assert probe.seen == {inside}
    assert torch.get_num_threads() == caller


def test_the_default_is_one_thread_and_a_loaded_agent_takes_its_own(tmp_path, pendulum_kwargs, caller_threads):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    assert model.n_threads == DEFAULT_THREADS == 1
    model.save(tmp_path / "model.zip")
    assert CMEPolicyIteration.load(tmp_path / "model.zip").n_threads == DEFAULT_THREADS  # like device: not saved
    assert CMEPolicyIteration.load(tmp_path / "model.zip", n_threads=2).n_threads == 2


@pytest.mark.parametrize("bad", [0, -1, 1.5, "2"])
def test_a_bad_thread_count_is_refused_by_name(bad):
    with pytest.raises(ValueError, match="n_threads"):
        CMEPolicyIteration("CMEPolicy", "Pendulum-v1", n_threads=bad)


def _small_config(*overrides: str):
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        return compose(
            config_name="config",
            overrides=[
                "total_timesteps=200",
                "eval_every=0",
                "eval_episodes=1",
                "verbose=0",
                "progress_bar=false",
                "agent.steps_per_iteration=100",
                "agent.evaluation.collection_size=300",
                "agent.exploration.random_steps=100",
                *overrides,
            ],
        )


@pytest.mark.parametrize(("overrides", "expected"), [((), DEFAULT_THREADS), (("n_threads=2",), 2)])
def test_train_py_goes_through_the_agents_n_threads(tmp_path, monkeypatch, caller_threads, overrides, expected):
    """train.py's n_threads (conf/config.yaml, default the library's) is the agent's, read during learn()."""
    cfg = _small_config(*overrides)
    probe = ThreadProbe()

    def dashboards_with_probe(*args, **kwargs):
        dashboards = training_dashboards(*args, **kwargs)
        dashboards.callbacks.append(probe)
        return dashboards

    monkeypatch.setattr(cme_agent.experiment, "training_dashboards", dashboards_with_probe)
    summary = run(cfg, tmp_path)
    assert summary["total_timesteps"] == 200
    assert probe.seen == {expected}
    assert probe.model.n_threads == expected
    assert torch.get_num_threads() == caller_threads
