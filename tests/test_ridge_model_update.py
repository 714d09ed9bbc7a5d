"""``model_update.method="ridge"``: B is the exact minimiser of the regularised loss on a fixed-size sample of D."""

import pytest
import torch

from cme_agent import CMEPolicyIteration
from cme_agent.config import MODEL_UPDATE_L2, ModelUpdateConfig


def _normal_equations_residual(agent: CMEPolicyIteration, l2: float) -> tuple[float, float]:
    """The gradient of (1/2N) sum ||y - B psi||^2 + (l2/2) ||B||^2 at the agent's B on all of D
    (times N), and the scale of its terms: (||B (Psi^T Psi + N l2 I) - Y^T Psi||, ||Y^T Psi||)."""
    dynamics = agent.dynamics
    psi, targets = dynamics.regression_data(agent.store.get(slice(0, len(agent.store))))
    psi, targets, weights = psi.double(), targets.double(), dynamics.weights.double()
    gram = psi.T @ psi + len(psi) * l2 * torch.eye(psi.shape[1], dtype=torch.float64)
    cross = targets.T @ psi
    return float(torch.linalg.norm(weights @ gram - cross)), float(torch.linalg.norm(cross))


def _agent(pendulum_kwargs, method: str, **model_update) -> CMEPolicyIteration:
    kwargs = {**pendulum_kwargs, "model_update": {**pendulum_kwargs["model_update"], "method": method, **model_update}}
    return CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **kwargs)


def test_ridge_solves_the_regularised_loss_on_all_of_d(pendulum_kwargs):
    agent = _agent(pendulum_kwargs, "ridge").learn(300)
    residual, scale = _normal_equations_residual(agent, agent.model_update_config.l2)
    assert agent.dynamics.q > 0
    assert residual < 1e-4 * scale


def test_sgd_does_not_reach_the_minimiser_that_ridge_finds(pendulum_kwargs):
    """The contrast that makes the test above able to fail: 20 SGD steps leave the gradient far from zero."""
    agent = _agent(pendulum_kwargs, "sgd").learn(300)
    residual, scale = _normal_equations_residual(agent, agent.model_update_config.l2)
    assert residual > 1e-2 * scale


def test_refit_reports_its_training_loss(pendulum_kwargs):
    agent = _agent(pendulum_kwargs, "ridge").learn(300)
    data = agent.store.get(slice(0, len(agent.store)))
    reported = agent.dynamics.refit_weights(data, agent.model_update_config.l2)
    psi, targets = agent.dynamics.regression_data(data)
    assert reported == pytest.approx(float(agent.dynamics.loss(psi, targets)), rel=1e-3)


def test_ridge_lowers_the_training_loss_below_sgd(pendulum_kwargs):
    losses = {}
    for method in ("sgd", "ridge"):
        agent = _agent(pendulum_kwargs, method).learn(300)
        psi, targets = agent.dynamics.regression_data(agent.store.get(slice(0, len(agent.store))))
        losses[method] = float(agent.dynamics.loss(psi, targets))
    assert losses["ridge"] < losses["sgd"]


@pytest.mark.parametrize(("refit_size", "expected"), [(10_000, None), (50, 50)])
def test_refit_sample_is_all_of_d_up_to_refit_size(pendulum_kwargs, refit_size, expected):
    agent = _agent(pendulum_kwargs, "ridge", refit_size=refit_size).learn(200)
    sample = agent.trainer.refit_sample(agent.store, agent._torch_rng)
    if expected is None:  # all of D, in order
        assert torch.equal(sample.obs, agent.store.get(slice(0, len(agent.store))).obs)
    else:
        assert len(sample) == expected < len(agent.store)


@pytest.mark.parametrize(("key", "value"), [("method", "lbfgs"), ("refit_size", 0)])
def test_bad_ridge_settings_name_the_key(key, value):
    with pytest.raises(ValueError, match=f"model_update.{key}"):
        ModelUpdateConfig(**{key: value})


def test_each_method_has_its_own_default_ridge_and_an_explicit_one_wins():
    assert ModelUpdateConfig().method == "ridge"
    assert ModelUpdateConfig().l2 == MODEL_UPDATE_L2["ridge"] == 1e-4
    assert ModelUpdateConfig(method="sgd").l2 == MODEL_UPDATE_L2["sgd"] == 1e-6
    assert ModelUpdateConfig(method="ridge", l2=1e-3).l2 == 1e-3
