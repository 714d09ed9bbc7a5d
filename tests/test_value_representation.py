"""benchmarks/diagnostics/value_representation.py: the nearest-neighbour reference, the kernels at
data states, the candidate maps' widths and metric, one measurement on a briefly trained agent, and
the trained agent saved with the transitions the candidates are fitted on."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from benchmarks.diagnostics import value_representation as vr
from benchmarks.diagnostics.gap_decomposition import trained_agent
from cme_agent import CMEPolicyIteration

pytest.importorskip("mujoco")


def test_knn_r2_is_near_one_on_a_smooth_target_and_not_on_noise() -> None:
    rng = np.random.default_rng(0)
    z = torch.as_tensor(rng.uniform(-1, 1, size=(4000, 2)))
    train = rng.random(4000) < 0.5
    smooth = np.sin(2 * z[:, 0].numpy()) + z[:, 1].numpy()
    assert vr.knn_r2(z, smooth, train, 3) > 0.99
    assert vr.knn_r2(z, rng.normal(size=4000), train, 3) < 0.1


def test_data_kernels_peak_at_their_centres_and_ignore_left_out_dims() -> None:
    centres = torch.tensor([[0.0, 5.0, 1.0], [2.0, -3.0, 1.0]])
    mean, inv_std = torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.5, 2.0, 0.0])  # dim 2 left out
    kernels = vr.DataKernels(centres, mean, inv_std, width=0.7)
    shifted = centres + torch.tensor([0.0, 0.0, 9.0])  # moves only the left-out dim
    features = kernels(shifted)
    assert features.shape == (2, 3)
    torch.testing.assert_close(features.diagonal(), torch.ones(2))
    torch.testing.assert_close(features[:, -1], torch.ones(2))
    distance = ((centres[0] - centres[1]) * inv_std).square().sum()
    assert float(features[0, 1]) == pytest.approx(math.exp(-float(distance) / (2 * 0.7**2)), rel=1e-5)


@pytest.fixture(scope="module")
def agent() -> CMEPolicyIteration:
    return CMEPolicyIteration("CMEPolicy", "InvertedDoublePendulum-v5", seed=0).learn(300)


def test_candidate_maps_have_p_and_2p_features_in_the_data_metric(agent: CMEPolicyIteration) -> None:
    data = agent.store.get(slice(0, len(agent.store))).obs
    maps = vr.candidate_maps(agent, data, seed=0)
    p = agent.dynamics.p
    assert set(maps) == {"agent"} | {
        f"{kind}_{w}_k{k}" for kind in ("fourier", "kernels") for w in (p, 2 * p) for k in vr.LENGTH_SCALES
    }
    for name, phi_map in maps.items():
        width = 2 * p if f"_{2 * p}_" in name else p
        if name.startswith("kernels"):
            width = min(width, len(data) + 1)  # at most one kernel per state of D
        assert phi_map(data[:5]).shape == (5, width)
    fourier = maps[f"fourier_{p}_k0.4"]
    torch.testing.assert_close(fourier.mean, data.mean(dim=0))
    varying = fourier.inv_std > 0
    torch.testing.assert_close(fourier.inv_std[varying], 1 / data.std(dim=0)[varying])


def test_measure_scores_every_candidate(agent: CMEPolicyIteration) -> None:
    rows = vr.measure(agent, "InvertedDoublePendulum-v5", 200, seed=0)
    p = agent.dynamics.p
    assert {"agent", f"kernels_{2 * p}_k0.8", "knn_1", "knn_10"} <= set(rows)
    for name, metrics in rows.items():
        expected = {"r2_fit"} if name.startswith("knn") else set(vr.METRICS)
        assert set(metrics) == expected
        assert all(math.isfinite(value) and value <= 1 for value in metrics.values())


def test_the_trained_agent_is_saved_with_its_transitions(tmp_path) -> None:
    path = tmp_path / "agent.zip"
    trained, seconds = trained_agent("InvertedDoublePendulum-v5", 0, 200, {}, path)
    loaded, loaded_seconds = trained_agent("InvertedDoublePendulum-v5", 0, 200, {}, path)
    assert seconds > 0 and loaded_seconds == 0.0
    assert len(loaded.store) == len(trained.store) > 0
    torch.testing.assert_close(
        loaded.store.get(slice(0, len(loaded.store))).obs, trained.store.get(slice(0, len(trained.store))).obs
    )


def test_measure_refuses_an_agent_without_its_transitions() -> None:
    untrained = CMEPolicyIteration("CMEPolicy", "InvertedDoublePendulum-v5", seed=0)
    with pytest.raises(SystemExit, match="without its transitions"):
        vr.measure(untrained, "InvertedDoublePendulum-v5", 200, seed=0)
