"""benchmarks/unseen_envs.py's report (no training): a held-out env's saved runs are reported beside
the suite but kept out of the suite's targets, and the suite's rows are unchanged by them."""

from __future__ import annotations

import csv
import dataclasses
import sys
from pathlib import Path

import pytest

from benchmarks import unseen_envs
from benchmarks.common import save_record


def _save_run(
    out: Path,
    agent: str,
    env: str,
    seed: int,
    final: float,
    curve: dict[int, float] | None = None,
    kwargs: str = "{}",
    stem: str = unseen_envs.STEM,
) -> unseen_envs.Job:
    """A complete run of 2,000 steps ending at ``final``, or of the last step of ``curve`` (steps -> return)."""
    curve = curve or {1_000: final - 1.0, 2_000: final}
    job = unseen_envs.Job(
        agent, env, seed, steps=max(curve), eval_every=1_000, out=str(out), command="test", kwargs=kwargs, stem=stem
    )
    evaluations = [
        {
            "steps": steps,
            "return_mean": value,
            "return_std": 0.0,
            "episode_length": 10,
            "train_seconds": 1.0,
            "train_cpu_seconds": 1.0,
            "eval_seconds": 0.1,
            "peak_rss_mib": 100.0,
            "n_features": 0,
        }
        for steps, value in curve.items()
    ]
    record = {"job": vars(job), "commit": "abc1234", "complete": True, "evaluations": evaluations, "peak_rss_mib": 100.0}
    if agent == "cme":
        record.update(box_expansions=0, phi_width=1_000, reward_source="learned")
    save_record(job.path, record)
    return job


def test_held_out_env_is_reported_but_not_a_target(tmp_path):
    for seed, final in enumerate((10.0, 20.0)):
        _save_run(tmp_path, "cme", "Swimmer-v5", seed, final)
        _save_run(tmp_path, "cme", "Reacher-v5", seed, -final)
        _save_run(tmp_path, "sac", "Reacher-v5", seed, -5.0)
    unseen_envs.report(list(unseen_envs.ENVS), 2_000, tmp_path)
    text = (tmp_path / "unseen_envs.md").read_text()
    summary = text.split("## Return by budget")[0]
    rows = [line for line in summary.splitlines() if line.startswith("| Swimmer-v5 | cme |")]
    assert len(rows) == 1 and "15.0 +- 7.1" in rows[0]
    targets = text.split("## Targets")[1].split("## Runs")[0]
    assert "Swimmer" not in targets
    assert (
        "within 10% of SAC's return at 2,000 steps on Reacher-v5: MISSED (CME -15.0 over 2 seeds, SAC -5.0 over 2, bar -5.5)"
        in targets
    )
    assert "ahead of SAC at 10,000 steps on Reacher-v5: not measured (0 CME, 0 SAC runs evaluated there)" in targets
    with open(tmp_path / "unseen_envs.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 12  # every evaluation of the 6 complete runs
    assert {(row["env"], row["agent"], row["seed"], row["steps"], row["return_mean"]) for row in rows} >= {
        ("Swimmer-v5", "cme", "1", "2000", "20.0"),
        ("Reacher-v5", "sac", "0", "1000", "-6.0"),
    }


def test_the_targets_are_ahead_at_10000_steps_within_10_percent_at_the_end_and_8_of_10_seeds(tmp_path):
    for seed in range(10):
        final = 1000.0 if seed < 8 else 500.0
        _save_run(tmp_path, "cme", "InvertedPendulum-v5", seed, 0.0, {5_000: final, 10_000: 1000.0, 20_000: 960.0})
    for seed in range(2):
        _save_run(tmp_path, "sac", "InvertedPendulum-v5", seed, 0.0, {5_000: 100.0, 10_000: 900.0, 20_000: 1000.0})
    unseen_envs.report(list(unseen_envs.ENVS), 20_000, tmp_path)
    targets = (tmp_path / "unseen_envs.md").read_text().split("## Targets")[1].split("## Runs")[0]
    assert "within 5,000 steps on 80% of seeds (CME): met (80%;" in targets
    assert "ahead of SAC at 10,000 steps on InvertedPendulum-v5: met (CME 1000.0 over 10 seeds, SAC 900.0 over 2" in targets
    assert "within 10% of SAC's return at 20,000 steps on InvertedPendulum-v5: met (CME 960.0" in targets


def test_held_out_env_without_runs_is_left_out(tmp_path):
    _save_run(tmp_path, "cme", "Reacher-v5", 0, -10.0)
    unseen_envs.report(list(unseen_envs.ENVS), 2_000, tmp_path)
    assert "Swimmer" not in (tmp_path / "unseen_envs.md").read_text()


def test_the_budget_table_says_where_cme_leads_and_where_it_falls_behind(tmp_path):
    for seed in (0, 1):
        _save_run(
            tmp_path, "cme", "InvertedPendulum-v5", seed, 0.0, {2_000: 50.0, 5_000: 400.0 + seed, 10_000: 700.0, 20_000: 700.0}
        )
        _save_run(
            tmp_path, "sac", "InvertedPendulum-v5", seed, 0.0, {2_000: 100.0, 5_000: 100.0, 10_000: 140.0, 20_000: 1000.0}
        )
    unseen_envs.report(list(unseen_envs.ENVS), 20_000, tmp_path)
    section = (tmp_path / "unseen_envs.md").read_text().split("## Return by budget")[1].split("## Targets")[0]
    assert "| InvertedPendulum-v5 | cme | 50.0 +- 0.0 | 400.5 +- 0.7 | 700.0 +- 0.0 | 700.0 +- 0.0 |" in section
    assert "| InvertedPendulum-v5 | sac | 100.0 +- 0.0 | 100.0 +- 0.0 | 140.0 +- 0.0 | 1000.0 +- 0.0 |" in section
    assert "- InvertedPendulum-v5: CME's mean above SAC's at 5,000, 10,000 env steps" in section


def test_a_setting_is_measured_under_its_own_stem_and_its_runs_are_not_taken_for_the_defaults(tmp_path):
    setting = '{"policy_kwargs": {"action_search": {"refine_steps": 10}}}'
    _save_run(tmp_path, "cme", "Reacher-v5", 0, -10.0)
    job = _save_run(tmp_path, "cme", "Reacher-v5", 0, -8.0, kwargs=setting, stem="unseen_envs_refine")
    assert job.path == tmp_path / "unseen_envs_refine" / "runs" / "cme_Reacher-v5_0.json"
    assert unseen_envs.is_done(job)
    assert not unseen_envs.is_done(dataclasses.replace(job, kwargs="{}"))  # other kwargs: run again
    unseen_envs.report(list(unseen_envs.ENVS), 2_000, tmp_path, "unseen_envs_refine")
    text = (tmp_path / "unseen_envs_refine.md").read_text()
    assert text.startswith("# Unseen envs: CME vs SB3 SAC vs random")
    assert f'`CMEPolicyIteration("CMEPolicy", env_id, seed=seed, **{setting})`' in text
    assert "| Reacher-v5 | cme | 0 | 2000 | -8.0 +- 0.0 |" in text
    assert (tmp_path / "unseen_envs_refine.csv").exists() and not (tmp_path / "unseen_envs.md").exists()
    unseen_envs.report(list(unseen_envs.ENVS), 2_000, tmp_path)
    defaults = (tmp_path / "unseen_envs.md").read_text()
    assert "at library defaults" in defaults and "| Reacher-v5 | cme | 0 | 2000 | -10.0 +- 0.0 |" in defaults


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--kwargs", "{gamma: 0.9}"], "--kwargs is not JSON"),
        (["--kwargs", "[0.9]", "--stem", "probe"], "--kwargs must be a JSON object"),
        (["--kwargs", '{"gamma": 0.9}'], "give the runs a --stem other than 'unseen_envs'"),
    ],
)
def test_bad_kwargs_are_refused_before_anything_runs(monkeypatch, capsys, tmp_path, arguments, message):
    monkeypatch.setattr(sys, "argv", ["unseen_envs", "--out", str(tmp_path), *arguments])
    with pytest.raises(SystemExit):
        unseen_envs.main()
    assert message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
