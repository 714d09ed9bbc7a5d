"""Numbers with a scale: train.py reports the return of random actions on the run's evaluation
episodes, and on Quadcopter-v0 the scripted controller's and the agent's fraction of it; the
quadcopter's pictures name its coordinates."""

from __future__ import annotations

import json
import logging

import pytest
from hydra import compose, initialize_config_dir

import cme_agent.pictures
from cme_agent import CMEPolicyIteration
from cme_agent.experiment import make_eval_env, run
from cme_agent.pictures import agent_pictures, observation_names
from cme_agent.references import RANDOM, Reference, controller_fraction, reference_returns
from tests.conftest import ROOT

QUADCOPTER_SMALL = [
    "env=quadcopter",
    "total_timesteps=200",
    "eval_every=0",
    "eval_episodes=2",
    "verbose=0",
    "progress_bar=false",
    "pictures_every=0",
    "agent.steps_per_iteration=100",
    "agent.evaluation.collection_size=300",
    "agent.exploration.random_steps=100",
    "agent.policy_kwargs.phi.n_fourier=50",
]


def _config(overrides):
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        return compose(config_name="config", overrides=overrides)


def test_the_quadcopter_run_reports_its_fraction_of_the_scripted_controller(tmp_path, caplog):
    cfg = _config(QUADCOPTER_SMALL)
    with caplog.at_level(logging.INFO, logger="cme_agent.experiment"):
        summary = run(cfg, tmp_path)
    saved = json.loads((tmp_path / "summary.json").read_text())
    controller = saved["references"]["scripted controller"]
    assert controller["mean_reward"] > saved["references"][RANDOM]["mean_reward"]  # it flies to the target
    assert saved["fraction_of_controller"] == pytest.approx(summary["eval_mean_reward"] / controller["mean_reward"])
    line = caplog.records[-1].getMessage()
    fraction = f"{saved['fraction_of_controller']:.2f} of the scripted controller's {controller['mean_reward']:.1f}"
    assert fraction in line and "random actions: " in line


def test_the_references_fly_the_evaluation_episodes_of_the_run():
    cfg = _config(["env=quadcopter", "seed=2"])
    first = reference_returns("Quadcopter-v0", lambda: make_eval_env(cfg), 2, seed=2)
    again = reference_returns("Quadcopter-v0", lambda: make_eval_env(cfg), 2, seed=2)
    assert [reference.name for reference in first] == [RANDOM, "scripted controller"]
    assert first == again  # the same starts and the same random actions: the same returns
    pendulum = _config(["env=pendulum"])
    assert [r.name for r in reference_returns("Pendulum-v1", lambda: make_eval_env(pendulum), 1, seed=0)] == [RANDOM]


@pytest.mark.parametrize(
    ("references", "fraction"),
    [
        ([Reference(RANDOM, 1.0, 0.0), Reference("scripted controller", 40.0, 1.0)], 0.5),
        ([Reference(RANDOM, 1.0, 0.0)], None),  # no controller
        ([Reference(RANDOM, -900.0, 0.0), Reference("scripted controller", -200.0, 1.0)], None),  # a ratio of costs
    ],
)
def test_the_fraction_of_the_controller(references, fraction):
    assert controller_fraction(20.0, references) == fraction


def test_the_quadcopters_pictures_name_its_coordinates(monkeypatch):
    names = observation_names("Quadcopter-v0")
    assert len(names) == 13 and names[:3] == ("x, north [m]", "y, east [m]", "z, down [m]")
    model = CMEPolicyIteration(
        "CMEPolicy",
        "Quadcopter-v0",
        seed=0,
        steps_per_iteration=100,
        evaluation={"collection_size": 300},
        exploration={"random_steps": 100},
        policy_kwargs={"phi": {"n_fourier": 50}},
    )
    model.learn(100)
    drawn_with = []
    folded_dims = cme_agent.pictures.folded_dims

    def recording(encoder, names=None, angle_names=None):
        drawn_with.append(names)
        return folded_dims(encoder, names, angle_names)

    monkeypatch.setattr(cme_agent.pictures, "folded_dims", recording)
    assert agent_pictures(model, resolution=8)
    assert drawn_with == [names]
