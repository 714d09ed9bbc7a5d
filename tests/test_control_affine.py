"""``feature_selection.control_affine``: the dictionary also offers atoms that ignore the action
(the state kernel alone) and atoms linear in it (the state kernel times one action coordinate),
so psi can represent a feature change affine in the action, f(s) + G(s) a."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gymnasium import spaces

from cme_agent import CMEPolicyIteration
from cme_agent.buffer import Transitions
from cme_agent.config import FeatureSelectionConfig
from cme_agent.dynamics import CMEDynamics
from cme_agent.dynamics.matching_pursuit import matching_pursuit
from cme_agent.kernel_bank import JOINT, STATE_ONLY, KernelBank, gaussian_kernel
from cme_agent.rewards import RewardSpec

OBS_SPACE = spaces.Box(np.full(2, -1.0, np.float32), np.full(2, 1.0, np.float32), dtype=np.float32)
ACTIONS_2D = spaces.Box(np.full(2, -2.0, np.float32), np.full(2, 2.0, np.float32), dtype=np.float32)
PHI = {"kind": "fourier", "max_width": 11}


def _mixed_bank() -> KernelBank:
    """A bank with two atoms of each kind: joint, state only, linear in z_a[0] and in z_a[1]."""
    generator = torch.Generator().manual_seed(0)
    bank = KernelBank(state_dim=2, action_dim=2)
    codes = torch.tensor([JOINT, JOINT, STATE_ONLY, STATE_ONLY, 0, 0, 1, 1])
    bank.append(torch.rand(8, 4, generator=generator) * 2 - 1, torch.full((8,), 0.5), codes)
    return bank


def test_each_atom_is_its_kind_and_factorises():
    bank = _mixed_bank()
    z = torch.rand(50, 4, generator=torch.Generator().manual_seed(1)) * 2 - 1
    z_s, z_a = z[:, :2], z[:, 2:]
    a = bank.inv_two_sq_bandwidth
    joint = gaussian_kernel(z, bank.centres, a)
    state = gaussian_kernel(z_s, bank.centres[:, :2], a)
    expected = torch.cat([joint[:, :2], state[:, 2:4], state[:, 4:6] * z_a[:, :1], state[:, 6:] * z_a[:, 1:]], dim=1)
    assert torch.allclose(bank(z), expected, atol=1e-6)
    assert torch.allclose(bank.state_factor(z_s) * bank.action_factor(z_a), expected, atol=1e-6)
    # the refinement's path: differentiable in the action
    z_grad = z.clone().requires_grad_(True)
    bank(z_grad)[:, 4:].sum().backward()
    assert torch.allclose(z_grad.grad[:, 2], state[:, 4:6].sum(1), atol=1e-5)


def test_the_codes_survive_save_and_load_and_an_old_file_loads_as_joint_atoms():
    bank = _mixed_bank()
    loaded = KernelBank(2, 2)
    loaded.load_state_dict(bank.state_dict())
    assert torch.equal(loaded.action_basis, bank.action_basis)
    z = torch.rand(5, 4)
    assert torch.equal(loaded(z), bank(z))
    old = {key: value for key, value in bank.state_dict().items() if key != "action_basis"}
    loaded.load_state_dict(old)
    assert torch.equal(loaded.action_basis, torch.full((8,), JOINT))


def test_the_dictionary_offers_each_kind_per_centre_and_bandwidth():
    dynamics = CMEDynamics(OBS_SPACE, ACTIONS_2D, PHI)
    z = torch.rand(30, 4) * 2 - 1
    atoms, columns = dynamics.dictionary(z, z[:5], torch.tensor([0.3, 0.6]), control_affine=True)
    assert atoms.shape == (30, 5 * 2 * 4)  # 5 centres x 2 bandwidths x (joint, state only, 2 linear)
    assert torch.equal(torch.bincount(columns.action_basis + 2), torch.tensor([10, 10, 10, 10]))
    bank = KernelBank(2, 2)
    bank.append(columns.centres, columns.bandwidths, columns.action_basis)
    assert torch.equal(atoms, bank(z))
    plain, plain_columns = dynamics.dictionary(z, z[:5], torch.tensor([0.3, 0.6]))
    assert plain.shape == (30, 10) and bool((plain_columns.action_basis == JOINT).all())


def _control_affine_system(n: int, generator: torch.Generator) -> Transitions:
    """s' = s + 0.05 (1 + s_0^2) a on [-0.8, 0.8]^2, actions uniform over the box (env units)."""
    obs = torch.rand(n, 2, generator=generator) * 1.6 - 0.8
    actions = torch.rand(n, 2, generator=generator) * 4 - 2
    next_obs = obs + 0.05 * (1 + obs[:, :1] ** 2) * actions
    return Transitions(obs, actions, torch.zeros(n), next_obs, torch.zeros(n, dtype=torch.bool))


def test_affine_atoms_fit_a_control_affine_system_with_few_features():
    """On s' = f(s) + G(s) a, the same number of features picked by matching pursuit (and B
    refit on them) predicts held-out transitions with less than half the error when the dictionary has the atoms
    linear in the action than with joint Gaussians only."""
    generator = torch.Generator().manual_seed(0)
    data, held_out = _control_affine_system(2000, generator), _control_affine_system(500, generator)
    errors = {}
    for affine in (False, True):
        dynamics = CMEDynamics(OBS_SPACE, ACTIONS_2D, PHI, reward=RewardSpec(_zero_reward))
        z = dynamics.encode(data.obs, data.actions)
        atoms, columns = dynamics.dictionary(z, z[:300], torch.tensor([0.3, 0.6]), control_affine=affine)
        result = matching_pursuit(atoms, dynamics.targets(data), 1e-6, 60)
        picked = columns[result.indices]
        dynamics.grow(picked.centres, picked.bandwidths, result.weights.T, picked.action_basis)
        dynamics.refit_weights(data, 1e-6)
        prediction = dynamics.predict(dynamics.features(held_out.obs, held_out.actions))
        errors[affine] = float(((prediction - dynamics.targets(held_out)) ** 2).sum(1).mean())
    assert errors[True] < 0.5 * errors[False], errors  # 0.017 against 0.075 here


def _zero_reward(obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    return torch.zeros(obs.shape[0])


def test_the_setting_is_validated_and_reaches_the_bank():
    with pytest.raises(ValueError, match=r"feature_selection\.control_affine"):
        FeatureSelectionConfig(control_affine="yes")
    agent = CMEPolicyIteration(
        "CMEPolicy", "Pendulum-v1", seed=0, steps_per_iteration=100, feature_selection={"control_affine": True}
    )
    agent.learn(400)
    basis = agent.policy.dynamics.psi.action_basis
    assert len(basis) == agent.policy.dynamics.q > 0
    assert bool((basis != JOINT).any())
