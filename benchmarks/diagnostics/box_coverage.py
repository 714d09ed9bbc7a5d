"""How well the observation box estimated from the random phase covers the data that follows
(normalisation without given bounds).

For each env, ``CMEPolicyIteration("CMEPolicy", env_id, seed=seed)`` (library defaults) learns
for ``--steps`` env steps, twice: with the box frozen after the random phase
(``observation.max_expansions=0``, the behaviour before expansion) and with the default
expansion (the box widened when an iteration's new data falls outside it). The final box is
then compared with the observations of the later half of its data: per observation dim, the
share of them outside the box and the largest |z| (z the normalised coordinate, [-1, 1] inside
the box). Envs with finite, usable bounds use those and are reported as such. Writes
results/box_coverage.md.

    python -m benchmarks.diagnostics.box_coverage [--envs PointGoal2D-v0 InvertedPendulum-v5] [--steps 3000] [--seed 0]
"""

from __future__ import annotations

import argparse

import torch

from benchmarks import unseen_envs
from benchmarks.common import command_line, markdown_table, with_cme, write_markdown
from cme_agent import CMEPolicyIteration


def coverage(env_id: str, steps: int, seed: int, max_expansions: int | None) -> list[str]:
    """One row: the box, the share of the later half of D outside it per dim, the largest |z| per dim.

    :param max_expansions: ``observation.max_expansions`` (None: the library default)
    """
    torch.set_num_threads(1)
    kwargs = {} if max_expansions is None else {"policy_kwargs": {"observation": {"max_expansions": max_expansions}}}
    model = CMEPolicyIteration("CMEPolicy", env_id, seed=seed, verbose=0, **with_cme(kwargs))
    model.learn(steps)
    encoder = model.dynamics.obs_encoder
    obs = model.store.get(slice(len(model.store) // 2, len(model.store))).obs
    z = encoder.normalize(obs).abs()
    low, high = encoder.center - encoder.half_range, encoder.center + encoder.half_range

    def cells(values: torch.Tensor, digits: int) -> str:
        return ", ".join(f"{float(v):.{digits}f}" for v in values)

    return [
        env_id,
        "frozen" if max_expansions == 0 else f"expanded {int(encoder.expansions)} time(s)",
        f"[{cells(low, 2)}] .. [{cells(high, 2)}]",
        cells((z > 1).float().mean(0), 2),
        cells(z.max(0).values, 1),
        str(model.q),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=[unseen_envs.CUSTOM_ENV, "InvertedPendulum-v5"])
    parser.add_argument("--steps", type=int, default=3_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rows = [coverage(env_id, args.steps, args.seed, expansions) for env_id in args.envs for expansions in (0, None)]
    header = [
        "env",
        "box after the random phase",
        "box (low .. high, env units)",
        "share of later data outside, per dim",
        "largest \\|z\\| per dim",
        "q",
    ]
    text = (
        f"# Coverage of the estimated observation box\n\nCommand: `{command_line()}`\n\n"
        f"Library defaults, seed {args.seed}, {args.steps:,} env steps; the box was estimated from the random "
        "phase (the first 400 steps: quantiles 0.01/0.99 widened by 0.1 of the range), then frozen or, by "
        "default, expanded to cover D whenever more than 5% of an iteration's new observations fell outside it "
        "(at most 4 times); 'later data' is the second half of the agent's transitions.\n\n"
        f"{markdown_table(header, rows)}\n"
    )
    write_markdown("box_coverage", text)


if __name__ == "__main__":
    main()
