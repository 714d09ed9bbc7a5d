"""The reporting logic of benchmarks/reproduce.py (no training): the run plan, growth exponents,
steps to a threshold and the choice of the best SB3 algorithm, on synthetic saved runs."""

from __future__ import annotations

import csv
import json
import math
import sys
from dataclasses import asdict, replace
from pathlib import Path

import pytest

from benchmarks import reproduce

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def saved_run(agent: str, env: str, seed: int, returns: list[float], period: int = 100) -> dict:
    """A saved run as ``reproduce.execute`` writes it, evaluated every ``period`` steps."""
    evaluations = [
        {"iteration": i + 1, "steps": (i + 1) * period, "train_seconds": 2.0 * (i + 1), "return_mean": value}
        for i, value in enumerate(returns)
    ]
    run = reproduce.Run(agent, env, seed, len(returns) * period, period)
    return {"run": asdict(run), "commit": "test", "seconds": 1.0, "evaluations": evaluations, "iterations": []}


@pytest.mark.parametrize("exponent", [0.0, 1.0, 3.0])
def test_growth_exponent_recovers_a_power_law(exponent: float) -> None:
    sizes = [100.0 * 2**i for i in range(10)]
    seconds = [1e-3 * size**exponent for size in sizes]
    assert reproduce.growth_exponent(sizes, seconds) == pytest.approx(exponent, abs=1e-6)


def test_growth_exponent_fits_only_the_second_half() -> None:
    sizes = [float(i) for i in range(1, 21)]
    seconds = [100.0] * 10 + [0.5 * size**2 for size in sizes[10:]]  # a warm-up first half
    assert reproduce.growth_exponent(sizes, seconds) == pytest.approx(2.0, abs=1e-6)


def test_reach_is_the_first_evaluation_at_or_above_the_threshold() -> None:
    run = saved_run("cme", "pendulum", 0, [-900.0, -200.0, -150.0, -400.0])
    assert reproduce.reach(run, -200.0) == (200, 4.0)
    assert reproduce.reach(run, -100.0) is None


def test_efficiency_takes_the_median_over_the_seeds_that_reached() -> None:
    runs = [
        saved_run("cme", "pendulum", 0, [-900.0, -150.0, -150.0]),
        saved_run("cme", "pendulum", 1, [-900.0, -900.0, -150.0]),
        saved_run("cme", "pendulum", 2, [-900.0, -900.0, -900.0]),
    ]
    stats = reproduce.efficiency(runs, -200.0)
    assert (stats["reached"], stats["seeds"]) == (2, 3)
    assert stats["steps"] == 250 and stats["seconds"] == 5.0
    assert stats["final"] == "-400.0 +- 433.0"
    assert math.isinf(reproduce.efficiency(runs[2:], -200.0)["steps"])


def test_sample_efficiency_names_the_sb3_algorithm_that_reached_on_most_seeds(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(sys, "argv", [str(BENCHMARKS / "reproduce.py"), "--only", "table", "--report-only"])
    runs_dir = tmp_path / "runs"
    runs_dir.mkdir()
    returns = {  # SAC reaches -200 first but on one seed only; TD3 on both, later
        ("cme", 0): [-900.0, -180.0],
        ("cme", 1): [-900.0, -190.0],
        ("sac", 0): [-150.0, -150.0],
        ("sac", 1): [-900.0, -900.0],
        ("td3", 0): [-900.0, -150.0],
        ("td3", 1): [-900.0, -150.0],
    }
    for (agent, seed), values in returns.items():
        (runs_dir / f"{agent}-pendulum-seed{seed}.json").write_text(json.dumps(saved_run(agent, "pendulum", seed, values)))
    other = saved_run("cme", "quadcopter", 0, [100.0]) | {"commit": "elsewhere"}  # a run the table does not draw
    (runs_dir / "cme-quadcopter-seed0.json").write_text(json.dumps(other))
    profile = replace(reproduce.PROFILES["quick"], table_seeds=(0, 1), table_envs=("pendulum",), sb3_agents=3, out=tmp_path)
    reproduce.sample_efficiency(profile, runs_dir)
    best, every = (tmp_path / "sample_efficiency.md").read_text().split("## Every algorithm")
    assert "made at commit `test`." in best  # the commits of the runs drawn, not of every saved run
    assert "best SB3: TD3 | 200 (2/2)" in best and "SAC" not in best
    assert "| MP | 200 (2/2)" in best
    assert "Kernel" not in every  # no saved Kernel runs: no row rather than an empty one
    assert "| SAC | 100 (1/2)" in every
    with open(tmp_path / "sample_efficiency.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 12  # every evaluation of the 6 runs drawn, none of the quadcopter run
    assert {(row["agent"], row["seed"], row["budget"], row["commit"]) for row in rows} >= {("td3", "1", "200", "test")}
    assert [float(row["return_mean"]) for row in rows if row["agent"] == "sac" and row["seed"] == "1"] == [-900.0, -900.0]


def test_full_plan_shares_runs_between_parts_and_has_no_duplicates() -> None:
    profile = reproduce.PROFILES["full"]
    runs = reproduce.planned_runs(list(reproduce.PARTS), profile)
    names = [run.name for run in runs]
    assert len(names) == len(set(names))
    table = reproduce.planned_runs(["table"], profile)
    sb3 = sum(len(agents) for agents, _ in reproduce.SB3_AGENTS.values())
    assert len(table) == len(profile.table_seeds) * (2 * len(profile.table_envs) + sb3)
    # the table's MP runs on Pendulum are figure 1's: the same length, so saved once
    shared = {run.name for run in table} & {run.name for run in reproduce.planned_runs(["figure1"], profile)}
    assert "cme-pendulum-seed0" in shared and "kernel-mountain_car-seed4" in shared


def test_mountain_car_mp_runs_keep_the_papers_sgd_update_and_others_their_config() -> None:
    sgd = "agent.model_update.method=sgd"
    assert reproduce.run_overrides(reproduce.Run("cme", "mountain_car", 0, 1000, 100)) == ["agent=cme", sgd]
    assert reproduce.run_overrides(reproduce.Run("cme", "mountain_car", 0, 1000, 1000, tag="scaling")) == ["agent=cme", sgd]
    assert reproduce.run_overrides(reproduce.Run("kernel", "mountain_car", 0, 1000, 100)) == ["agent=kernel"]
    assert reproduce.run_overrides(reproduce.Run("cme", "pendulum", 0, 1000, 100)) == ["agent=cme"]


def test_quick_plan_is_shorter_than_the_full_one() -> None:
    quick = {run.name: run for run in reproduce.planned_runs(["figure1"], reproduce.PROFILES["quick"])}
    full = {run.name: run for run in reproduce.planned_runs(["figure1"], reproduce.PROFILES["full"])}
    assert set(quick) < set(full)
    assert all(quick[name].steps < full[name].steps for name in quick)


def test_collapse_distances_split_the_second_half_by_half_the_reference() -> None:
    run = saved_run("cme", "quadcopter", 0, [10.0, 150.0, 40.0, 160.0])
    for row, distance in zip(run["evaluations"], [9.0, 0.5, 6.0, 0.7], strict=True):
        row["final_distance"] = distance
    collapsed, others = reproduce.collapse_distances([run], reference=180.0, from_steps=200)
    assert collapsed == [6.0] and others == [0.5, 0.7]
    assert reproduce.distance_summary(others) == "median 0.60 m (range 0.50 to 0.70 m)"
    assert reproduce.distance_summary([]) == "none"
