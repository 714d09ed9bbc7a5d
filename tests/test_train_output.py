"""What train.py prints by default: a progress bar, a line per evaluation, SB3's table every
log_interval iterations and the result, well under 100 lines for the quickstart's run; every
table at verbose=2."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir

from tests.conftest import ROOT, run_train

QUICKSTART_SHAPE = [
    "total_timesteps=600",  # 30 iterations and 6 evaluations, as the default Pendulum run's 6,000 steps
    "agent.steps_per_iteration=20",
    "eval_every=100",
    "eval_episodes=1",
    "agent.evaluation.collection_size=300",
    "agent.exploration.random_steps=100",
    "agent.policy_kwargs.phi.resolution=[9,7]",
]


def test_the_defaults_show_a_progress_bar_and_a_table_every_10_iterations():
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose(config_name="config")
    assert cfg.progress_bar is True and cfg.verbose == 1 and cfg.log_interval == 10


def test_the_quickstart_run_prints_under_100_lines(tmp_path):
    result = run_train(tmp_path, *QUICKSTART_SHAPE)
    assert result.returncode == 0, result.stderr
    lines = (result.stdout + result.stderr).splitlines()
    assert len(lines) < 100, "\n".join(lines)
    assert sum(line.startswith("| time/") for line in lines) == 3  # SB3's table at iterations 10, 20, 30
    evaluations = [line for line in lines if line.startswith("evaluation at ")]
    assert [line.split()[2] for line in evaluations] == ["100", "200", "300", "400", "500", "600"]
    (bar,) = [line for line in lines if "600/600" in line]  # the bar's last state, with the last evaluation
    assert "100%" in bar and "eval " in bar
    last = result.stdout.splitlines()[-1]
    assert "return" in last and "random actions" in last  # the result, with a scale


@pytest.mark.parametrize(("verbose", "tables"), [("verbose=2", 36), ("verbose=0", 0)])
def test_verbose_2_prints_every_table_and_0_none(tmp_path, verbose, tables):
    result = run_train(tmp_path, *QUICKSTART_SHAPE, verbose, "progress_bar=false")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    # every iteration's table and every evaluation's (which has a time/ section too)
    assert sum(line.startswith("| time/") for line in lines) == tables
    assert not any("600/600" in line for line in lines)
