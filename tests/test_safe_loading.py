"""Model files are safe to load: nothing but JSON and tensors is read, and bad files fail clearly."""

import io
import json
import os
import zipfile

import pytest
import torch

from cme_agent import CMEPolicyIteration, KernelPolicyIteration
from cme_agent.serialization import META, TENSORS, ModelFileError


class _RunsCode:
    """Unpickling this object would run a shell command."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.fixture
def saved(tmp_path, pendulum_kwargs):
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **pendulum_kwargs)
    model.learn(200)
    path = tmp_path / "model.zip"
    model.save(path)
    return path


def _rewrite(source, target, name, content):
    with zipfile.ZipFile(source) as archive:
        members = {member: archive.read(member) for member in archive.namelist()}
    members[name] = content
    with zipfile.ZipFile(target, "w") as archive:
        for member, data in members.items():
            archive.writestr(member, data)


def test_a_file_crafted_to_run_code_is_refused(saved, tmp_path):
    marker = tmp_path / "pwned"
    buffer = io.BytesIO()
    torch.save({"policy": _RunsCode(marker)}, buffer)
    crafted = tmp_path / "crafted.zip"
    _rewrite(saved, crafted, TENSORS, buffer.getvalue())
    with pytest.raises(ModelFileError, match="refused"):
        CMEPolicyIteration.load(crafted)
    assert not marker.exists()


def test_the_file_holds_only_json_and_tensors(saved):
    with zipfile.ZipFile(saved) as archive:
        assert sorted(archive.namelist()) == sorted([META, TENSORS])
        meta = json.loads(archive.read(META))
    assert meta["init"]["gamma"] == 0.98 and meta["state"]["iteration"] > 0


@pytest.mark.parametrize("cut", [0.3, 0.9])
def test_truncated_file_gives_a_clear_error(saved, tmp_path, cut):
    data = saved.read_bytes()
    truncated = tmp_path / "truncated.zip"
    truncated.write_bytes(data[: int(len(data) * cut)])
    with pytest.raises(ModelFileError, match="not a readable cme_agent model file"):
        CMEPolicyIteration.load(truncated)


def test_foreign_files_give_clear_errors(tmp_path):
    from stable_baselines3 import PPO

    ppo = tmp_path / "ppo.zip"
    PPO("MlpPolicy", "CartPole-v1", n_steps=64).save(ppo)
    with pytest.raises(ModelFileError, match="not a cme_agent model file"):
        CMEPolicyIteration.load(ppo)
    junk = tmp_path / "junk.zip"
    junk.write_bytes(os.urandom(1000))
    with pytest.raises(ModelFileError, match="truncated or not a zip"):
        CMEPolicyIteration.load(junk)
    with pytest.raises(ModelFileError, match="no model file"):
        CMEPolicyIteration.load(tmp_path / "missing.zip")


def test_corrupt_description_gives_a_clear_error(saved, tmp_path):
    corrupt = tmp_path / "corrupt.zip"
    _rewrite(saved, corrupt, META, b"{not json")
    with pytest.raises(ModelFileError, match="corrupt"):
        CMEPolicyIteration.load(corrupt)
    mismatched = tmp_path / "mismatched.zip"
    meta = json.loads(zipfile.ZipFile(saved).read(META))
    meta["init"]["policy_kwargs"]["phi"]["resolution"] = [5, 5]  # another phi width than the tensors have
    _rewrite(saved, mismatched, META, json.dumps(meta).encode())
    with pytest.raises(ModelFileError, match="does not match"):
        CMEPolicyIteration.load(mismatched)


def test_wrong_class_is_named(saved):
    with pytest.raises(ModelFileError, match="holds a CMEPolicyIteration"):
        KernelPolicyIteration.load(saved)


def test_custom_phi_must_be_passed_again(tmp_path, pendulum_kwargs):
    phi = torch.nn.Linear(3, 5)
    kwargs = {**pendulum_kwargs, "policy_kwargs": {"phi": phi}}
    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **kwargs)
    model.learn(200)
    model.save(tmp_path / "custom.zip")
    with pytest.raises(ModelFileError, match="custom phi"):
        CMEPolicyIteration.load(tmp_path / "custom.zip")
    loaded = CMEPolicyIteration.load(tmp_path / "custom.zip", policy_kwargs={"phi": torch.nn.Linear(3, 5)})
    assert torch.equal(loaded.policy.dynamics.phi.feature_map.weight, phi.weight)  # the weights come from the file


def test_save_is_atomic(saved, monkeypatch, pendulum_kwargs):
    """A crash while writing leaves the previous file intact and no temporary behind."""
    before = saved.read_bytes()
    model = CMEPolicyIteration.load(saved)

    def crash(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("cme_agent.serialization.os.replace", crash)
    with pytest.raises(KeyboardInterrupt):
        model.save(saved)
    assert saved.read_bytes() == before
    assert [p.name for p in saved.parent.iterdir() if p.name.endswith(".tmp")] == []
