"""model_update.kind="auto": the model of the observation where s' - s is linear in (s, a), else the CME."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from cme_agent import CMEPolicyIteration
from cme_agent.buffer import Transitions
from cme_agent.config import ModelUpdateConfig
from cme_agent.dynamics.observation import ObservationModel, change_r2
from cme_agent.kernel_baseline import KernelPolicyIteration
from cme_agent.presets import preset_files

PLAIN = {"preset": False, "verbose": 0}
WAVES = 500
"""model_update.change_fourier of the tests with waves."""


def synthetic(n: int, seed: int, smooth: bool = False) -> Transitions:
    """Dims 0-1 change linearly in (s, a), dim 2 by sin(3 s_0) (nonlinear; ``smooth``: by s_0 s_1, as a Coriolis
    term), dim 3 never changes."""
    generator = torch.Generator().manual_seed(seed)
    obs, actions = torch.randn(n, 4, generator=generator), torch.rand(n, 1, generator=generator) * 2 - 1
    obs[:, 3] = 0.0
    bend = obs[:, 0] * obs[:, 1] if smooth else torch.sin(3 * obs[:, 0])
    change = torch.stack([0.1 * obs[:, 1], -0.2 * obs[:, 0] + 0.5 * actions[:, 0], bend, torch.zeros(n)], dim=1)
    return Transitions(obs, actions, torch.zeros(n), obs + change, torch.zeros(n, dtype=torch.bool))


def state_of(model: CMEPolicyIteration) -> dict[str, torch.Tensor]:
    return {**model.policy.state_dict(), **{f"store.{k}": v for k, v in model.store.state_dict().items()}}


def test_the_held_out_r2_is_one_where_the_change_is_linear_and_low_where_it_is_not() -> None:
    r2 = change_r2(synthetic(400, seed=0), synthetic(100, seed=1))
    assert r2.shape == (4,)
    assert float(r2[0]) > 0.999 and float(r2[1]) > 0.999
    assert float(r2[2]) < 0.5  # sin(3 s_0) is not linear in s_0
    assert float(r2[3]) == pytest.approx(1.0)  # a constant change is explained


def test_waves_of_s_and_a_explain_a_smooth_nonlinear_change_the_linear_model_misses() -> None:
    train, held_out = synthetic(400, seed=0, smooth=True), synthetic(500, seed=1, smooth=True)
    linear, waves = change_r2(train, held_out), change_r2(train, held_out, WAVES)
    assert float(linear[2]) < 0.1 and float(waves[2]) > 0.99
    assert bool((waves[[0, 1, 3]] > 0.999).all())  # the linear part stays exact


def test_the_waves_survive_save_load_and_a_file_saved_before_them_loads_linear(tmp_path) -> None:
    model = ObservationModel(4, 1, WAVES)
    data = synthetic(400, seed=0, smooth=True)
    model.fit(data)
    torch.save(model.state_dict(), tmp_path / "model.pt")
    loaded = ObservationModel(4, 1, WAVES)
    loaded.load_state_dict(torch.load(tmp_path / "model.pt"))
    torch.testing.assert_close(loaded.next_obs(data.obs, data.actions), model.next_obs(data.obs, data.actions))
    linear = ObservationModel(4, 1)
    linear.fit(data)
    legacy = {key: value for key, value in linear.state_dict().items() if not key.startswith("change_features.")}
    fresh = ObservationModel(4, 1)
    fresh.load_state_dict(legacy)
    torch.testing.assert_close(fresh.next_obs(data.obs, data.actions), linear.next_obs(data.obs, data.actions))


def test_the_waves_hold_each_input_within_its_range_on_the_data() -> None:
    model = ObservationModel(4, 1, WAVES)
    data = synthetic(400, seed=0, smooth=True)
    model.fit(data)
    obs, actions = synthetic(50, seed=1, smooth=True).obs.double(), data.actions[:50].double()
    # dim 3 is 0 on every transition: a rolled-out state 1e-3 off it (1,000 of its clamped standard deviations)
    # moves only that dim, by its own 1e-3, instead of reaching waves the fit never saw
    off = obs.clone()
    off[:, 3] = 1e-3
    moved = model.next_obs(off, actions) - model.next_obs(obs, actions)
    torch.testing.assert_close(moved, torch.zeros_like(moved).index_fill_(1, torch.tensor([3]), 1e-3), atol=1e-9, rtol=0)
    # beyond the data's range in dim 0 the waves stay at their value at its edge
    features, edge = model.change_features, data.obs[:, 0].double().max()
    far, at_edge = obs.clone(), obs.clone()
    far[:, 0], at_edge[:, 0] = edge + 5.0, edge
    linear = torch.cat([far, actions, torch.ones(50, 1, dtype=far.dtype)], dim=1)
    linear_edge = torch.cat([at_edge, actions, torch.ones(50, 1, dtype=far.dtype)], dim=1)
    torch.testing.assert_close(features.waves(linear), features.waves(linear_edge))
    legacy = {key: value for key, value in model.state_dict().items() if key != "change_features.input_range"}
    unbounded = ObservationModel(4, 1, WAVES)
    unbounded.load_state_dict(legacy)  # a file saved before the range predicts as it did: unbounded
    assert bool(unbounded.change_features.input_range.isinf().all())


def test_an_agent_with_waves_learns_acts_and_survives_save_load(tmp_path) -> None:
    waves = {"kind": "observation", "change_fourier": WAVES}
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, model_update=waves, **PLAIN).learn(400)
    assert model.policy.lookahead.model.change_features.phase.numel() == WAVES
    model.save(tmp_path / "waves.zip")
    loaded = CMEPolicyIteration.load(tmp_path / "waves.zip")
    assert loaded.model_update_config.change_fourier == WAVES
    obs = model.store.get(slice(0, 50)).obs.numpy()
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])


def test_auto_chooses_the_observation_model_on_cartpole_and_the_cme_on_pendulum(capsys) -> None:
    cartpole = CMEPolicyIteration("CMEPolicy", "CartPole-v1", seed=0, **{**PLAIN, "verbose": 1}).learn(500)
    said = capsys.readouterr().out
    assert "model_update.kind='auto' chose the model of the observation" in said and "R^2 of 1.000" in said
    assert cartpole.model_update_config.kind == cartpole.policy.model_kind == "observation"
    assert cartpole.policy.lookahead is not None and cartpole.q == 0
    pendulum = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **PLAIN).learn(400)
    assert pendulum.model_update_config.kind == pendulum.policy.model_kind == "cme"
    assert pendulum.policy.lookahead is None and pendulum.q > 0
    assert not any(key.startswith("lookahead.") for key in pendulum.policy.state_dict())


@pytest.mark.parametrize(("env_id", "kind", "steps"), [("CartPole-v1", "observation", 600), ("Pendulum-v1", "cme", 400)])
def test_auto_makes_the_run_the_chosen_kind_makes_from_the_start(env_id: str, kind: str, steps: int) -> None:
    auto = CMEPolicyIteration("CMEPolicy", env_id, seed=3, **PLAIN).learn(steps)
    fixed = CMEPolicyIteration("CMEPolicy", env_id, seed=3, model_update={"kind": kind}, **PLAIN).learn(steps)
    assert auto.policy.model_kind == kind
    auto_state, fixed_state = state_of(auto), state_of(fixed)
    assert auto_state.keys() == fixed_state.keys()
    for key, value in auto_state.items():
        torch.testing.assert_close(value, fixed_state[key], rtol=0, atol=0, msg=key)


def test_the_choice_survives_save_load_and_an_unchosen_agent_chooses_after_loading(tmp_path) -> None:
    model = CMEPolicyIteration("CMEPolicy", "CartPole-v1", seed=1, **PLAIN).learn(500)
    model.save(tmp_path / "chosen.zip")
    loaded = CMEPolicyIteration.load(tmp_path / "chosen.zip")
    assert loaded.model_update_config.kind == loaded.policy.model_kind == "observation"
    torch.testing.assert_close(loaded.policy.lookahead.value_weights, model.policy.lookahead.value_weights)
    obs = model.store.get(slice(0, 50)).obs.numpy()
    assert (loaded.predict(obs, deterministic=True)[0] == model.predict(obs, deterministic=True)[0]).all()
    fresh = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=1, **PLAIN)
    fresh.save(tmp_path / "fresh.zip")
    reloaded = CMEPolicyIteration.load(tmp_path / "fresh.zip", env=gym.make("Pendulum-v1"))
    assert reloaded.policy.model_kind == "auto" and reloaded.policy.lookahead is not None
    assert reloaded.learn(400).policy.model_kind == "cme" and reloaded.policy.lookahead is None


def test_the_presets_keep_the_cme_they_were_measured_with() -> None:
    for env_id in preset_files():
        model = CMEPolicyIteration("CMEPolicy", env_id, seed=0, verbose=0)
        assert model.model_update_config.kind == model.policy.model_kind == "cme", env_id
        assert model.policy.lookahead is None, env_id


def test_auto_keeps_the_cme_with_the_soft_improvement_and_refines_either_model() -> None:
    soft = CMEPolicyIteration("CMEPolicy", "CartPole-v1", seed=0, improvement={"method": "soft"}, **PLAIN)
    assert soft.policy.model_kind == "cme" and soft.policy.lookahead is None
    refined = CMEPolicyIteration(
        "CMEPolicy", "Pendulum-v1", seed=0, policy_kwargs={"action_search": {"refine_steps": 2}}, **PLAIN
    )
    assert refined.policy.model_kind == "auto" and refined.policy.lookahead is not None and refined.policy.refines


def test_without_held_out_transitions_auto_keeps_the_cme(capsys) -> None:
    model = CMEPolicyIteration("CMEPolicy", "CartPole-v1", seed=0, model_update={"holdout_fraction": 0.0}, **PLAIN)
    model.verbose = 1
    model.learn(400)
    assert model.policy.model_kind == "cme" and model.policy.lookahead is None
    assert "fewer than 10 held-out transitions" in capsys.readouterr().out


def test_the_threshold_is_checked_and_the_kernel_baseline_stays_a_cme() -> None:
    for bad in (0.0, 1.5, "high"):
        with pytest.raises(ValueError, match=r"model_update\.auto_r2"):
            ModelUpdateConfig(auto_r2=bad)
    for bad in (-1, 1.5, True, "many"):
        with pytest.raises(ValueError, match=r"model_update\.change_fourier"):
            ModelUpdateConfig(change_fourier=bad)
    assert ModelUpdateConfig().kind == "auto" and ModelUpdateConfig().change_fourier == 0
    with pytest.raises(ValueError, match="invalid for the Kernel baseline"):
        KernelPolicyIteration("CMEPolicy", "CartPole-v1", model_update={"kind": "observation"}, **PLAIN)
    kernel = KernelPolicyIteration("CMEPolicy", "CartPole-v1", **PLAIN)
    assert kernel.policy.model_kind == "cme" and kernel.policy.lookahead is None
