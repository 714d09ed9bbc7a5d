"""Property-based tests (hypothesis) of the numerical core."""

import numpy as np
import pytest
import torch
from gymnasium import spaces
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from cme_agent import CMEPolicy, CMEPolicyIteration, RewardSpec
from cme_agent.dynamics import matching_pursuit
from cme_agent.planning import smooth

finite = st.floats(-10, 10, allow_nan=False, width=32)


@settings(max_examples=60, deadline=None)
@given(
    atoms=arrays(np.float32, st.tuples(st.integers(5, 40), st.integers(1, 30)), elements=st.floats(0, 1, width=32)),
    outputs=st.integers(1, 5),
    seed=st.integers(0, 2**16),
    threshold=st.floats(1e-6, 0.5),
    theta=st.floats(0, 1),
    orthogonal=st.booleans(),
)
def test_matching_pursuit_never_raises_the_loss(atoms, outputs, seed, threshold, theta, orthogonal):
    generator = torch.Generator().manual_seed(seed)
    residual = torch.randn(atoms.shape[0], outputs, generator=generator) * 3
    G = torch.from_numpy(atoms)
    result = matching_pursuit(G, residual, threshold, max_atoms=10, orthogonal=orthogonal)
    before = float((residual.double() ** 2).sum())
    after = float(((residual.double() - theta * G[:, result.indices].double() @ result.weights.double()) ** 2).sum())
    assert after <= before * (1 + 1e-9) + 1e-9


@settings(max_examples=100, deadline=None)
@given(
    previous=arrays(np.float32, st.integers(0, 20), elements=finite),
    extra=st.integers(0, 10),
    omega=st.floats(0, 1),
    data=st.data(),
)
def test_q_smoothing_is_a_convex_combination(previous, extra, omega, data):
    estimate = data.draw(arrays(np.float32, len(previous) + extra, elements=finite))
    old, new = torch.from_numpy(previous), torch.from_numpy(estimate)
    smoothed = smooth(old, new, omega)
    padded = torch.nn.functional.pad(old, (0, extra))
    low, high = torch.minimum(padded, new), torch.maximum(padded, new)
    tolerance = 1e-5 * (1 + high.abs())
    assert torch.all(smoothed >= low - tolerance) and torch.all(smoothed <= high + tolerance)


action_spaces = st.one_of(
    st.integers(2, 6).map(spaces.Discrete),
    st.tuples(st.integers(1, 4), st.floats(0.1, 5)).map(lambda d: spaces.Box(-d[1], d[1] * 2, (d[0],), np.float32)),
)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(space=action_spaces, seed=st.integers(0, 2**16), refine=st.integers(0, 5))
def test_greedy_actions_always_lie_in_the_action_space(space, seed, refine):
    generator = torch.Generator().manual_seed(seed)
    obs_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
    policy = CMEPolicy(
        obs_space,
        space,
        phi={"resolution": [4]},
        action_search={"refine_steps": refine, "refine_lr": 0.5, "n_samples": 32},
        reward=RewardSpec(lambda obs, a: torch.zeros(obs.shape[0])),
    )
    dynamics = policy.dynamics
    centres = torch.rand(12, 2 + dynamics.action_encoder.dim, generator=generator) * 4 - 2
    dynamics.grow(centres, torch.rand(12, generator=generator) + 0.05, torch.zeros(dynamics.weights.shape[0], 12))
    policy.theta_psi = torch.randn(12, generator=generator) * 10
    obs = torch.rand(16, 2, generator=generator) * 4 - 2  # also outside the observation box
    actions, _ = policy.greedy(obs)
    for action in actions.numpy():
        assert space.contains(action.astype(space.dtype) if not isinstance(space, spaces.Discrete) else int(action))


@pytest.fixture(scope="module")
def trained_pendulum(tmp_path_factory):
    from tests.conftest import small_kwargs

    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, **small_kwargs())
    model.learn(300)
    path = tmp_path_factory.mktemp("model") / "m.zip"
    model.save(path)
    return model, CMEPolicyIteration.load(path)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(obs=arrays(np.float32, (20, 3), elements=st.floats(-8, 8, width=32)))
def test_save_load_is_the_identity_on_predictions(trained_pendulum, obs):
    model, loaded = trained_pendulum
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
