"""save() -> load() after the feature bank has grown."""

import json
import os
import stat
import zipfile

import numpy as np
import pytest
import torch
from gymnasium import spaces

from cme_agent import CMEPolicyIteration
from cme_agent.dynamics import CMEDynamics
from cme_agent.serialization import META


def test_save_load_after_growth_gives_identical_actions(tmp_path, pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    model.learn(400)
    assert model.q > 0
    path = tmp_path / "pendulum_cme.zip"
    model.save(path)
    loaded = CMEPolicyIteration.load(path)
    assert loaded.q == model.q
    rng = np.random.default_rng(0)
    angles = rng.uniform(-np.pi, np.pi, 64)
    obs = np.stack([np.cos(angles), np.sin(angles), rng.uniform(-8, 8, 64)], 1).astype(np.float32)
    expected, _ = model.predict(obs, deterministic=True)
    actual, _ = loaded.predict(obs, deterministic=True)
    np.testing.assert_array_equal(actual, expected)
    for name in ("theta_psi", "theta_phi"):
        np.testing.assert_array_equal(getattr(loaded.policy, name).numpy(), getattr(model.policy, name).numpy())
    np.testing.assert_array_equal(loaded.dynamics.weights.numpy(), model.dynamics.weights.numpy())


def test_the_model_update_method_survives_save_load_and_older_files_load_as_sgd(tmp_path, pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    model.learn(200)
    path = tmp_path / "model.zip"
    model.save(path)
    assert model.model_update_config.method == "ridge"
    assert CMEPolicyIteration.load(path).model_update_config.method == "ridge"
    with zipfile.ZipFile(path) as archive:  # a file written before model_update.method existed
        members = {member: archive.read(member) for member in archive.namelist()}
    meta = json.loads(members[META])
    del meta["init"]["model_update"]["method"]
    members[META] = json.dumps(meta).encode()
    older = tmp_path / "older.zip"
    with zipfile.ZipFile(older, "w") as archive:
        for member, data in members.items():
            archive.writestr(member, data)
    assert CMEPolicyIteration.load(older).model_update_config.method == "sgd"  # what it was trained with


def test_loaded_model_keeps_learning(tmp_path, pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    model.learn(200)
    model.save(tmp_path / "m.zip")
    loaded = CMEPolicyIteration.load(tmp_path / "m.zip", env=model.get_env())
    before = loaded.q
    loaded.learn(200, reset_num_timesteps=False)
    assert loaded.num_timesteps == 400
    assert loaded.q >= before
    assert loaded.dynamics.weights.shape[1] == loaded.policy.theta_psi.shape[0] == loaded.q


def test_user_reward_must_be_given_again(tmp_path, pendulum_kwargs):
    from cme_agent.rewards import KNOWN_REWARDS

    reward = KNOWN_REWARDS["Pendulum-v1"].step_reward
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", reward_fn=reward, **pendulum_kwargs)
    model.save(tmp_path / "m.zip")
    with pytest.raises(ValueError, match="reward_fn"):
        CMEPolicyIteration.load(tmp_path / "m.zip")
    assert CMEPolicyIteration.load(tmp_path / "m.zip", reward_fn=reward).reward_source == "user"


def test_learn_without_an_env_says_how_to_give_one(tmp_path, pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    model.learn(100)
    model.save(tmp_path / "m.zip")
    with pytest.raises(ValueError, match=r"load\(path, env=...\) or call set_env"):
        CMEPolicyIteration.load(tmp_path / "m.zip").learn(100)


@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_saved_files_follow_the_umask(tmp_path, pendulum_kwargs, umask):
    """model.zip and checkpoint.zip get 0666 less the umask (0644 under the usual 022), not mkstemp's 0600."""
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    previous = os.umask(umask)
    try:
        model.save(tmp_path / "model.zip")
        model.save(tmp_path / "checkpoint.zip", include=["replay_buffer"])
        model.save(tmp_path / "model.zip")  # replacing a file keeps the rule
    finally:
        os.umask(previous)
    for name in ("model.zip", "checkpoint.zip"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o666 & ~umask, name
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.zip", "model.zip"]  # no temporary left


def test_a_model_saved_with_the_removed_learned_metric_loads_only_where_it_was_isotropic():
    box = spaces.Box(np.full(2, -1.0, np.float32), np.full(2, 1.0, np.float32), dtype=np.float32)
    dynamics = CMEDynamics(box, box, {"kind": "fourier", "max_width": 11})
    dynamics.load_state_dict({**dynamics.state_dict(), "state_metric": torch.ones(2)})  # never fitted: the same kernels
    with pytest.raises(ValueError, match="learned metric"):
        dynamics.load_state_dict({**dynamics.state_dict(), "state_metric": torch.tensor([1.0, 2.0])})
