"""Would another phi represent V^pi better? The value of the agent's policy on a MuJoCo env, phi by phi.

Trains (or loads) ``CMEPolicyIteration("CMEPolicy", env_id, seed=seed)`` as gap_decomposition.py
does, builds the same C (half the agent's deterministic episodes, half with its training noise;
simulator states recorded) with pi's true transitions and Monte-Carlo values V^pi, and scores each
candidate phi on C's odd episodes:

- ``r2_true_w``: R^2 of <w, phi> against V^pi, w by eq. (7) on C through the true transitions with
  the agent's gamma and ridge (the value a perfect model would give the agent);
- ``r2_fit``, ``r2_fit_train``: the best ridge fit of V^pi on phi (gap_decomposition.best_phi_fit),
  held out and on its own rows.

Candidates, at p and 2p features (p the agent's width): the agent's phi; random Fourier features in
the data metric (``phi.metric="data"``: each dim in its standard deviation over the agent's data D)
of length scale k sqrt(d), d the dims that vary in D; Gaussian kernels of width k sqrt(d) in the
same metric centred at states of D drawn at random (at most one per state; a phi that sits where the data is); and, as a
reference that needs no basis, the mean of V^pi over the k nearest even-episode states in the data
metric (``knn_<k>``, ``r2_fit`` only): where it is no better than the agent's phi, V^pi is rough at
the data's density and no phi will represent it much better.

Each seed's model goes to results/<stem>/<env>_seed<k>.zip and its record to .json (scratch); the
report to results/<stem>.md.

    python -m benchmarks.diagnostics.value_representation --env-id InvertedDoublePendulum-v5 --seeds 0 1 2 --steps 10000
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from benchmarks.common import SeedFiles, add_seed_arguments, command_line, map_seeds, markdown_table, write_markdown
from benchmarks.diagnostics.gap_decomposition import (
    COLLECTION_SEED_OFFSET,
    best_phi_fit,
    collection,
    monte_carlo_values,
    recorded_row,
    simulate,
)
from benchmarks.diagnostics.true_dynamics_planning import r_squared, rollout_horizon
from cme_agent import CMEPolicyIteration
from cme_agent.planning import bellman_residual_weights
from cme_agent.state_features import RandomFourierFeatures

LENGTH_SCALES = (0.2, 0.4, 0.8)
"""k of the candidates' length scale k sqrt(d), in standard deviations of the data."""
NEIGHBOURS = (1, 3, 10)
"""k of the nearest-neighbour references."""
METRICS = ("r2_true_w", "r2_fit", "r2_fit_train")


class DataKernels(torch.nn.Module):
    """Gaussian kernels centred at given states, in the data metric, and the constant feature:
    phi(s) = (exp(-||z(s) - z(c_j)||^2 / (2 h^2)), 1), z = (s - mean) * inv_std.

    :param centres: (m, obs_dim) centres, env units
    :param mean: (obs_dim,) the data's mean
    :param inv_std: (obs_dim,) the inverse standard deviations (0 for a dim left out)
    :param width: h, in standard deviations
    """

    def __init__(self, centres: torch.Tensor, mean: torch.Tensor, inv_std: torch.Tensor, width: float) -> None:
        super().__init__()
        self.mean, self.inv_std, self.width = mean, inv_std, width
        self.centres = (centres - mean) * inv_std

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """:param obs: (N, obs_dim) states. :return: (N, m + 1) features."""
        distances = torch.cdist((obs - self.mean) * self.inv_std, self.centres).square_()
        return torch.cat([distances.div_(-2 * self.width**2).exp_(), torch.ones_like(distances[:, :1])], dim=1)


def candidate_maps(agent: CMEPolicyIteration, data: torch.Tensor, seed: int) -> dict[str, Any]:
    """The phi maps compared, by name: the agent's, and Fourier features and kernels at states of
    ``data`` (N, obs_dim) in its metric, at each length scale, at p and 2p features."""
    generator = torch.Generator().manual_seed(seed)
    maps: dict[str, Any] = {"agent": agent.dynamics.phi}
    encoder, p = agent.dynamics.phi.encoder, agent.dynamics.p
    for width in (p, 2 * p):
        for k in LENGTH_SCALES:
            fourier = RandomFourierFeatures(encoder, width - 1, 1.0, seed=seed + width, metric="data")
            fourier.fit(data)
            d = int((fourier.inv_std > 0).sum())
            fourier.projection.div_(k * math.sqrt(d))
            maps[f"fourier_{width}_k{k}"] = fourier
            centres = data[torch.randperm(len(data), generator=generator)[: width - 1]]
            maps[f"kernels_{width}_k{k}"] = DataKernels(centres, fourier.mean, fourier.inv_std, k * math.sqrt(d))
    return maps


def knn_r2(z: torch.Tensor, values: np.ndarray, train: np.ndarray, k: int) -> float:
    """R^2 on the rows not in ``train`` of the mean of ``values`` over each row's k nearest
    ``train`` rows (Euclidean in z).

    :param z: (N, d) coordinates
    :param values: (N,) targets
    :param train: (N,) bool, the rows that are neighbours
    :param k: neighbours averaged
    """
    targets = torch.as_tensor(values, dtype=torch.float64)
    train_rows, test_rows = torch.as_tensor(train), torch.as_tensor(~train)
    nearest = torch.cdist(z[test_rows], z[train_rows]).topk(k, largest=False).indices
    prediction = targets[train_rows][nearest].mean(dim=1)
    truth = targets[test_rows]
    return float(1 - (prediction - truth).square().mean() / (truth - truth.mean()).square().mean())


@torch.no_grad()
def measure(agent: CMEPolicyIteration, env_id: str, collection_size: int, seed: int) -> dict[str, Any]:
    """Every candidate's R^2 on one trained agent: ``{name: {metric: value}}``."""
    if len(agent.store) == 0:
        raise SystemExit("the agent was saved without its transitions D: use another --stem")
    sim = gym.make(env_id).unwrapped
    gamma, l2 = agent.gamma, agent.evaluation_config.l2
    states, _ = collection(agent, env_id, collection_size, seed + COLLECTION_SEED_OFFSET)
    held_out = states.episode % 2 == 1
    actions = agent.predict(states.obs.astype(np.float32), deterministic=True)[0]
    true = simulate(sim, states.qpos, states.qvel, actions)
    continuation = torch.as_tensor(~true.terminated, dtype=torch.float32)[:, None]
    rewards = torch.as_tensor(true.rewards, dtype=torch.float32)
    values = monte_carlo_values(agent, sim, states, rollout_horizon(gamma))
    obs, next_obs = (torch.as_tensor(x, dtype=torch.float32) for x in (states.obs, true.obs))
    data = agent.store.get(slice(0, len(agent.store))).obs
    rows: dict[str, Any] = {}
    maps = candidate_maps(agent, data, seed)
    for name, phi_map in maps.items():
        phi = phi_map(obs)
        weights = bellman_residual_weights(phi, phi_map(next_obs) * continuation, rewards, gamma, l2)
        fit, fit_train = best_phi_fit(phi, values, ~held_out)
        rows[name] = {
            "r2_true_w": r_squared(weights, phi[held_out], values[held_out]),
            "r2_fit": fit,
            "r2_fit_train": fit_train,
        }
    metric = maps[f"fourier_{agent.dynamics.p}_k{LENGTH_SCALES[0]}"]
    z = (obs - metric.mean) * metric.inv_std
    for k in NEIGHBOURS:
        rows[f"knn_{k}"] = {"r2_fit": knn_r2(z, values, ~held_out, k)}
    return rows


@dataclass(frozen=True)
class Job(SeedFiles):
    """One seed: train ``env_id`` for ``steps`` env steps (constructor arguments ``kwargs``), then
    measure on ``collection`` states; files under results/<stem>/."""

    env_id: str
    seed: int
    steps: int
    kwargs: dict[str, Any]
    collection: int
    stem: str


def run_seed(job: Job) -> dict[str, Any]:
    """Train (or load) one agent and measure it, or read the record of an earlier run."""
    return recorded_row(job, lambda agent: {"phi": measure(agent, job.env_id, job.collection, job.seed)})


def report(args: argparse.Namespace, rows: list[dict[str, Any]]) -> str:
    """The markdown report: per candidate, each metric's mean over seeds (and per seed)."""
    table = []
    for name, first in rows[0]["phi"].items():
        cells = []
        for metric in METRICS:
            if metric not in first:
                cells.append("-")
                continue
            per_seed = [row["phi"][name][metric] for row in rows]
            cells.append(f"{statistics.mean(per_seed):.3f} ({', '.join(f'{v:.2f}' for v in per_seed)})")
        table.append([name, *cells])
    return "\n".join(
        [
            f"# The value of pi on {args.env_id}, phi by phi: R^2 against Monte Carlo\n",
            f"Command: `{command_line()}`.\n",
            f'`CMEPolicyIteration("CMEPolicy", {args.env_id!r}, seed=seed, **{json.loads(args.kwargs)})` trained for '
            f"{args.steps} env steps; C: {args.collection} states of its episodes; scored on C's odd episodes. Each cell: the "
            "mean over seeds (per seed in brackets). Definitions: the module docstring of "
            "`benchmarks/diagnostics/value_representation.py`.\n",
            markdown_table(["phi", *METRICS], table) + "\n",
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="InvertedDoublePendulum-v5", help="a MuJoCo env id with a Box action space")
    add_seed_arguments(parser, "")
    parser.add_argument("--collection", type=int, default=4_000, help="|C|: states where the candidates are scored")
    parser.set_defaults(workers=1)
    args = parser.parse_args()
    args.stem = args.stem or f"value_representation_{args.env_id}"
    jobs = [Job(args.env_id, seed, args.steps, json.loads(args.kwargs), args.collection, args.stem) for seed in args.seeds]
    write_markdown(args.stem, report(args, map_seeds(run_seed, jobs, args.workers)))


if __name__ == "__main__":
    main()
