"""Envs the library was never tuned on, with library defaults: CME vs SB3 SAC vs random.

The suite: InvertedPendulum-v5, InvertedDoublePendulum-v5 and Reacher-v5 (MuJoCo, extra
``mujoco``: ``pip install -e ".[mujoco]"``), whose observation bounds are infinite, and
``PointGoal2D-v0`` (:class:`cme_agent.envs.point_goal.PointGoal2D`, registered by ``import cme_agent``):
a 2-D point mass that must reach a goal only the env knows (no ``reward_function``: the agent
learns the reward). No env has a preset.

Held-out envs, run only when named in ``--envs``: ``Swimmer-v5`` (MuJoCo, 2-D action, 1,000-step
episodes) and ``LunarLanderContinuous-v3`` (Box2D, extra ``box2d``; 2-D action: main and lateral
engines), kept out of the suite so that a default chosen on the suite can be checked on envs that
did not choose it. They are reported beside the suite, not in the suite's targets.

One job is (agent, env, seed), run in a fresh process (so its peak memory is its own):

- ``cme``: ``CMEPolicyIteration("CMEPolicy", env_id, seed=seed)``, nothing else; with ``--kwargs``
  (JSON) ``CMEPolicyIteration("CMEPolicy", env_id, seed=seed, **kwargs)``, a setting measured on the
  suite against the defaults (give it its own ``--stem``);
- ``sac``: ``SAC("MlpPolicy", env_id, seed=seed)``, SB3's defaults (learning_starts=100,
  buffer_size=1e6, batch_size=256, train_freq=1, ...), on the CPU;
- ``random``: uniform random actions, evaluated once on 100 episodes (a reference line);
- ``zero``: the action space's centre (zero torque on the MuJoCo envs) at every step, evaluated
  the same way: the return of doing nothing, which a policy that has learned little matches.

Every ``--eval-every`` env steps the learning agents are evaluated on 10 episodes of the
deterministic policy, on a separate env seeded ``seed + 10_000``. Each job writes its curve to
``results/<stem>/runs/<agent>_<env>_<seed>.json`` (stem ``unseen_envs`` by default) after every
evaluation (return, steps, wall-clock and thread CPU seconds of training, the process's peak RSS so
far) and marks it complete at the end; complete runs (of the same steps and kwargs) are skipped, so
the script can be stopped and run again (an incomplete run restarts from scratch).
``--report-only`` writes ``results/<stem>.md``, ``results/<stem>.csv`` (every evaluation of every
complete run) and ``results/<stem>.png`` from the saved runs.

    python -m benchmarks.unseen_envs                       # the whole suite: 3 seeds, 20,000 steps
    python -m benchmarks.unseen_envs --seeds 0 --agents cme --envs InvertedPendulum-v5
    python -m benchmarks.unseen_envs --agents cme --stem unseen_envs_frozen_box \
        --kwargs '{"policy_kwargs": {"observation": {"max_expansions": 0}}}'
    python -m benchmarks.unseen_envs --report-only
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import resource
import statistics
import time
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import VecEnv

import cme_agent  # noqa: F401  (registers PointGoal2D-v0, in the spawned job processes too)
from benchmarks.common import (
    RESULTS,
    code_version,
    command_line,
    machine,
    markdown_table,
    pyplot,
    resident_bytes,
    save_record,
    write_csv,
)
from cme_agent.references import RandomPolicy

CUSTOM_ENV = "PointGoal2D-v0"
ENVS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Reacher-v5", CUSTOM_ENV)
REPORTED_ENVS = ("HalfCheetah-v5", "Hopper-v5")
"""Envs of the suite reported without a target: larger bodies (17 and 11 observation dims, 6 and 3 action dims)."""
HELD_OUT_ENVS = ("Swimmer-v5", "LunarLanderContinuous-v3")
"""Envs outside the suite, run on request only (``--envs``): the check of a default on an env that did not pick it."""
AGENTS = ("cme", "sac", "random", "zero")
LEARNERS = ("cme", "sac")
REFERENCES = ("random", "zero")
STEM = "unseen_envs"
"""The default name of the report files and of the runs' folder in the results folder."""
TARGET_ENV, TARGET_RETURN, TARGET_STEPS, TARGET_SHARE = "InvertedPendulum-v5", 950.0, 5_000, 0.8
"""InvertedPendulum-v5 at or above 950 within 5,000 env steps on 80% of the seeds."""
AHEAD_STEPS = 10_000
"""Env steps at which CME should be ahead of SAC on every env of ``ENVS``."""
BUDGETS = (2_000, 5_000, 10_000)
"""Env-step budgets below the runs' last at which the report compares the learners (the last is always added)."""
EVAL_EPISODES = 10
RANDOM_EPISODES = 100
EVAL_SEED_OFFSET = 10_000
MIB = 2**20


@dataclass(frozen=True)
class Job:
    """One run: ``agent`` on ``env`` with ``seed`` for ``steps`` env steps, evaluated every ``eval_every``.

    :param out: the results folder; the record goes to ``<out>/<stem>/runs/``
    :param command: the command and commit that started it (for the report)
    :param kwargs: constructor arguments of CME beyond the env and the seed, as JSON
    :param stem: the name of the runs' folder and of the report
    """

    agent: str
    env: str
    seed: int
    steps: int
    eval_every: int
    out: str = str(RESULTS)
    command: str = ""
    kwargs: str = "{}"
    stem: str = STEM

    @property
    def path(self) -> Path:
        return runs_dir(Path(self.out), self.stem) / f"{self.agent}_{self.env}_{self.seed}.json"


def runs_dir(out: Path, stem: str = STEM) -> Path:
    """Where the job records of a report ``stem`` in a results folder go."""
    return out / stem / "runs"


class ZeroAgent:
    """The centre of a Box action space at every step (zero torque), with SB3's ``predict``.

    :param action_space: the env's ``Box`` action space
    """

    def __init__(self, action_space: spaces.Box) -> None:
        self.action = ((action_space.low + action_space.high) / 2).astype(action_space.dtype)

    def predict(self, observation: np.ndarray, state: Any = None, episode_start: Any = None, deterministic: bool = False):
        """The centre, once per observation of the batch."""
        return np.repeat(self.action[None], len(observation), axis=0), None


def make_learner(agent: str, env_id: str, seed: int, kwargs: dict[str, Any]) -> Any:
    """The agent at library defaults: CME with nothing but the env, the seed and ``kwargs``; SAC at SB3's defaults.

    :param agent: ``cme`` or ``sac``
    :param env_id: the Gymnasium id
    :param seed: the seed of the agent (and of its training env)
    :param kwargs: CME's further constructor arguments (empty: the defaults)
    """
    if agent == "cme":
        from cme_agent import CMEPolicyIteration

        model = CMEPolicyIteration("CMEPolicy", env_id, seed=seed, **kwargs)
    elif agent == "sac":
        from stable_baselines3 import SAC

        model = SAC("MlpPolicy", env_id, seed=seed, device="cpu")
    else:
        raise ValueError(f"unknown learning agent {agent!r}; known: {LEARNERS}")
    model.set_logger(configure(None, []))
    return model


def evaluate(model: Any, env: VecEnv, episodes: int) -> dict[str, float]:
    """Mean, std and mean length of ``episodes`` episodes of the deterministic policy.

    :param model: anything with SB3's ``predict``
    :param env: the evaluation env (seeded apart from training)
    :param episodes: the number of episodes
    """
    returns, lengths = evaluate_policy(model, env, n_eval_episodes=episodes, deterministic=True, return_episode_rewards=True)
    return {
        "return_mean": statistics.mean(returns),
        "return_std": statistics.pstdev(returns),
        "episode_length": statistics.mean(lengths),
    }


def peak_rss_mib() -> float:
    """Peak resident memory of this process so far, MiB (``ru_maxrss`` is in KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run_job(job: Job) -> str:
    """Train and evaluate one job in this (fresh) process, saving its record after every evaluation.

    :return: a line for the progress log
    """
    torch.set_num_threads(1)
    record: dict[str, Any] = {
        "job": asdict(job),
        "commit": code_version(),
        "machine": machine(),
        "complete": False,
        "rss_before_agent_mib": resident_bytes() / MIB,
        "evaluations": [],
    }
    eval_env = make_vec_env(job.env, n_envs=1, seed=job.seed + EVAL_SEED_OFFSET)
    if job.agent in REFERENCES:
        start = time.perf_counter()
        agent = RandomPolicy(eval_env.action_space, job.seed) if job.agent == "random" else ZeroAgent(eval_env.action_space)
        row = {"steps": 0, **evaluate(agent, eval_env, RANDOM_EPISODES)}
        record["evaluations"].append({**row, "eval_seconds": time.perf_counter() - start, "peak_rss_mib": peak_rss_mib()})
    else:
        model = make_learner(job.agent, job.env, job.seed, json.loads(job.kwargs))
        train_wall = train_cpu = eval_wall = 0.0
        while model.num_timesteps < job.steps:
            wall, cpu = time.perf_counter(), time.thread_time()
            model.learn(min(job.eval_every, job.steps - model.num_timesteps), reset_num_timesteps=False)
            train_wall += time.perf_counter() - wall
            train_cpu += time.thread_time() - cpu
            wall = time.perf_counter()
            row = {"steps": int(model.num_timesteps), **evaluate(model, eval_env, EVAL_EPISODES)}
            eval_wall += time.perf_counter() - wall
            row.update(
                train_seconds=round(train_wall, 2),
                train_cpu_seconds=round(train_cpu, 2),
                eval_seconds=round(eval_wall, 2),
                peak_rss_mib=round(peak_rss_mib(), 1),
                n_features=int(getattr(model, "q", 0)),
            )
            record["evaluations"].append(row)
            save_record(job.path, record)
            print(f"{job.agent} {job.env} seed {job.seed} steps {row['steps']}: {row['return_mean']:.1f}", flush=True)
        if job.agent == "cme":
            record["box_expansions"] = int(model.dynamics.obs_encoder.expansions)
            record["phi_width"] = int(model.dynamics.p)
            record["reward_source"] = model.reward_source
    record["complete"] = True
    record["peak_rss_mib"] = round(peak_rss_mib(), 1)
    save_record(job.path, record)
    final = record["evaluations"][-1]
    return f"{job.agent} {job.env} seed {job.seed}: {final['return_mean']:.1f} (peak {record['peak_rss_mib']:.0f} MiB)"


def run_job_safely(job: Job) -> str:
    """:func:`run_job`, a failure kept in the job's record (``error``) instead of stopping the suite."""
    try:
        return run_job(job)
    except Exception:
        record = load_record(job.path) or {"job": asdict(job), "commit": code_version(), "evaluations": []}
        record.update(complete=False, error=traceback.format_exc())
        save_record(job.path, record)
        return f"{job.agent} {job.env} seed {job.seed}: FAILED\n{record['error']}"


def load_record(path: Path) -> dict[str, Any] | None:
    """The saved record of a job, or None if there is none."""
    return json.loads(path.read_text()) if path.exists() else None


def planned_jobs(
    agents: list[str],
    envs: list[str],
    seeds: list[int],
    steps: int,
    eval_every: int,
    out: Path,
    kwargs: str = "{}",
    stem: str = STEM,
) -> list[Job]:
    """The jobs in the order they run: the random and zero references first (seconds each), then
    seed by seed CME on every env, then SAC on every env. ``kwargs`` (JSON) goes to CME only."""
    command = command_line()
    order = [(agent, seed) for seed in seeds for agent in REFERENCES] + [(agent, seed) for seed in seeds for agent in LEARNERS]
    return [
        Job(agent, env, seed, steps, eval_every, str(out), command, kwargs if agent == "cme" else "{}", stem)
        for agent, seed in order
        if agent in agents
        for env in envs
    ]


def is_done(job: Job) -> bool:
    """Whether the job's record is complete, for the same number of steps and the same kwargs."""
    record = load_record(job.path)
    return (
        record is not None
        and record["complete"]
        and record["job"]["steps"] == job.steps
        and json.loads(record["job"].get("kwargs", "{}")) == json.loads(job.kwargs)
    )


def run_all(jobs: list[Job], workers: int) -> None:
    """Run the jobs that are not complete, ``workers`` at a time, each in a fresh process."""
    todo = [job for job in jobs if not is_done(job)]
    print(f"{len(jobs) - len(todo)} of {len(jobs)} jobs already complete; running {len(todo)}", flush=True)
    if not todo:
        return
    with multiprocessing.get_context("spawn").Pool(workers, maxtasksperchild=1) as pool:
        for done, line in enumerate(pool.imap_unordered(run_job_safely, todo, chunksize=1), start=1):
            print(f"[{done}/{len(todo)}] {line}", flush=True)


# ---------------------------------------------------------------------- report
def saved_runs(out: Path, stem: str = STEM) -> list[dict[str, Any]]:
    """Every saved record (complete or not) of the report ``stem`` in a results folder."""
    return [json.loads(path.read_text()) for path in sorted(runs_dir(out, stem).glob("*.json"))]


def _mean_std(values: list[float]) -> str:
    spread = statistics.stdev(values) if len(values) > 1 else 0.0
    return f"{statistics.mean(values):.1f} +- {spread:.1f}"


def last_step(run: dict[str, Any]) -> int:
    """The step count of a run's last evaluation (0 before the first)."""
    return run["evaluations"][-1]["steps"] if run["evaluations"] else 0


def steps_to_target(run: dict[str, Any]) -> int | None:
    """The first evaluated step count at which the return reached the InvertedPendulum target."""
    return next((row["steps"] for row in run["evaluations"] if row["return_mean"] >= TARGET_RETURN), None)


def random_level(complete: dict[tuple[str, str], list[dict[str, Any]]], env: str) -> float | None:
    """The mean return of the random agent on ``env`` over its seeds (None: not run)."""
    runs = complete.get((env, "random"), [])
    return statistics.mean(run["evaluations"][0]["return_mean"] for run in runs) if runs else None


def summary_row(env: str, agent: str, runs: list[dict[str, Any]], random: float | None) -> list[Any]:
    """One line of the table: final returns over the complete seeds (and above random), the best
    evaluation, costs per run, peak memory.

    :param random: the random agent's mean return on ``env`` (None: not run)
    """
    finals = [run["evaluations"][-1]["return_mean"] for run in runs]
    seeds = ", ".join(str(run["job"]["seed"]) for run in runs)
    peak = max(run["peak_rss_mib"] for run in runs)
    if agent in REFERENCES:
        episodes = f"{RANDOM_EPISODES} episodes per seed"
        return [
            env,
            agent,
            seeds,
            "-",
            _mean_std(finals),
            "-",
            f"{min(finals):.1f}",
            "-",
            "-",
            "-",
            "-",
            f"{peak:.0f}",
            episodes,
        ]
    last = [run["evaluations"][-1] for run in runs]
    best = [max(row["return_mean"] for row in run["evaluations"]) for run in runs]
    reached = "-"
    if env == TARGET_ENV:
        reached = ", ".join(str(steps_to_target(run) or "never") for run in runs)
    return [
        env,
        agent,
        seeds,
        str(last[0]["steps"]),
        _mean_std(finals),
        "-" if random is None else f"{statistics.mean(finals) - random:+.1f}",
        f"{min(finals):.1f}",
        f"{statistics.mean(best):.1f}",
        reached,
        f"{statistics.mean(row['train_seconds'] for row in last):.0f}",
        f"{statistics.mean(row['train_cpu_seconds'] for row in last):.0f}",
        f"{peak:.0f}",
        f"eval {statistics.mean(row['eval_seconds'] for row in last):.0f} s/run"
        + (f"; p = {runs[0]['phi_width']}, q = {last[0]['n_features']}" if agent == "cme" else ""),
    ]


def partial_row(run: dict[str, Any]) -> list[Any]:
    """One line for a run that did not complete: how far it got and what it had reached."""
    rows = run["evaluations"]
    if not rows:
        return [run["job"]["env"], run["job"]["agent"], run["job"]["seed"], 0, "-", "-", "-", "-", "-"]
    last = rows[-1]
    curve = ", ".join(f"{row['return_mean']:.0f}" for row in rows)
    return [
        run["job"]["env"],
        run["job"]["agent"],
        run["job"]["seed"],
        last["steps"],
        f"{last['return_mean']:.1f}",
        f"{max(row['return_mean'] for row in rows):.1f}",
        f"{last['train_seconds']:.0f}",
        f"{last['peak_rss_mib']:.0f}",
        curve,
    ]


def verdicts(complete: dict[tuple[str, str], list[dict[str, Any]]], steps: int) -> list[str]:
    """The targets, each said met, missed or not measured, with the numbers: InvertedPendulum-v5 at
    950 within 5,000 steps on 8 seeds in 10, and on every env of ``ENVS`` CME ahead of SAC at
    10,000 steps and within 10% of SAC's return at the end (``steps``)."""
    lines = []
    cme_target = complete.get((TARGET_ENV, "cme"), [])
    if cme_target:
        reached = [steps_to_target(run) for run in cme_target]
        share = sum(r is not None and r <= TARGET_STEPS for r in reached) / len(reached)
        lines.append(
            f"- {TARGET_ENV} >= {TARGET_RETURN:g} within {TARGET_STEPS:,} steps on {TARGET_SHARE:.0%} of seeds (CME): "
            f"{'met' if share >= TARGET_SHARE else 'MISSED'} ({share:.0%}; first evaluation at or above it, per seed: "
            f"{', '.join(str(r or 'never') for r in reached)})"
        )
    else:
        lines.append(f"- {TARGET_ENV} >= {TARGET_RETURN:g} within {TARGET_STEPS:,} steps: not measured (no complete CME run)")
    for env in ENVS:
        cme, sac = complete.get((env, "cme"), []), complete.get((env, "sac"), [])
        for budget, rule in ((AHEAD_STEPS, "ahead of SAC"), (steps, "within 10% of SAC's return")):
            cme_returns = [r for r in (return_at(run, budget) for run in cme) if r is not None]
            sac_returns = [r for r in (return_at(run, budget) for run in sac) if r is not None]
            if not cme_returns or not sac_returns:
                lines.append(
                    f"- {rule} at {budget:,} steps on {env}: not measured "
                    f"({len(cme_returns)} CME, {len(sac_returns)} SAC runs evaluated there)"
                )
                continue
            cme_mean, sac_mean = statistics.mean(cme_returns), statistics.mean(sac_returns)
            bar = sac_mean if rule == "ahead of SAC" else sac_mean - 0.1 * abs(sac_mean)
            met = cme_mean > bar if rule == "ahead of SAC" else cme_mean >= bar
            lines.append(
                f"- {rule} at {budget:,} steps on {env}: {'met' if met else 'MISSED'} (CME {cme_mean:.1f} over "
                f"{len(cme_returns)} seeds, SAC {sac_mean:.1f} over {len(sac_returns)}, bar {bar:.1f})"
            )
    peaks = [run["peak_rss_mib"] for runs in complete.values() for run in runs if run["job"]["agent"] == "cme"]
    if peaks:
        verdict = "met" if max(peaks) <= 1024 else "MISSED"
        lines.append(f"- CME peak memory <= 1 GiB on every env run: {verdict} (largest {max(peaks):.0f} MiB, whole process)")
    return lines


def return_at(run: dict[str, Any], steps: int) -> float | None:
    """A run's evaluation return at ``steps`` env steps (None: not evaluated there)."""
    return next((row["return_mean"] for row in run["evaluations"] if row["steps"] == steps), None)


def by_budget(complete: dict[tuple[str, str], list[dict[str, Any]]], envs: list[str], steps: int) -> list[str]:
    """The learners' returns at each budget of :data:`BUDGETS` below ``steps`` and at ``steps``
    (mean +- std over the seeds evaluated there), and per env the budgets at which CME's mean is
    above SAC's: where the model-based agent is ahead, not only at the end.

    :param steps: the runs' planned length in env steps (the last budget)
    :return: the section's lines (a table, then one line per env with both agents)
    """
    budgets = [budget for budget in BUDGETS if budget < steps] + [steps]

    def returns(runs: list[dict[str, Any]], budget: int) -> list[float]:
        return [value for value in (return_at(run, budget) for run in runs) if value is not None]

    rows, ahead = [], []
    for env in envs:
        for agent in LEARNERS:
            runs = complete.get((env, agent), [])
            if runs:
                rows.append([env, agent, *(_mean_std(values) if (values := returns(runs, b)) else "-" for b in budgets)])
        cme, sac = complete.get((env, "cme"), []), complete.get((env, "sac"), [])
        if cme and sac:
            leads = [
                f"{budget:,}"
                for budget in budgets
                if returns(cme, budget)
                and returns(sac, budget)
                and statistics.mean(returns(cme, budget)) > statistics.mean(returns(sac, budget))
            ]
            ahead.append(f"- {env}: CME's mean above SAC's at {', '.join(leads) + ' env steps' if leads else 'no budget'}")
    header = ["env", "agent", *(f"return at {budget:,} steps" for budget in budgets)]
    return [markdown_table(header, rows), "", *ahead] if rows else ["No complete run of a learning agent."]


def plot(complete: dict[tuple[str, str], list[dict[str, Any]]], envs: list[str], path: Path) -> None:
    """results/<stem>.png: a panel per env of ``envs``, each seed thin, the mean thick, random dashed, zero dash-dot."""
    plt = pyplot()
    if plt is None:
        return
    fig, axes = plt.subplots(1, len(envs), figsize=(4.5 * len(envs), 3.8), squeeze=False)
    colours = {"cme": "tab:blue", "sac": "tab:orange"}
    for ax, env in zip(axes[0], envs, strict=True):
        for agent, colour in colours.items():
            runs = complete.get((env, agent), [])
            for run in runs:
                ax.plot(
                    [r["steps"] for r in run["evaluations"]],
                    [r["return_mean"] for r in run["evaluations"]],
                    color=colour,
                    alpha=0.3,
                )
            if runs:
                shared = min(len(run["evaluations"]) for run in runs)
                steps = [runs[0]["evaluations"][i]["steps"] for i in range(shared)]
                mean = [statistics.mean(run["evaluations"][i]["return_mean"] for run in runs) for i in range(shared)]
                ax.plot(steps, mean, color=colour, linewidth=2, label=f"{agent} (mean of {len(runs)})")
        for reference, style in zip(REFERENCES, ("--", "-."), strict=True):
            reference_runs = complete.get((env, reference), [])
            if reference_runs:
                level = statistics.mean(run["evaluations"][0]["return_mean"] for run in reference_runs)
                ax.axhline(level, color="grey", linestyle=style, label=reference)
        if env == TARGET_ENV:
            ax.axhline(TARGET_RETURN, color="red", linestyle=":", label=f"target {TARGET_RETURN:g}")
            ax.axvline(TARGET_STEPS, color="red", linestyle=":", linewidth=0.8)
        ax.set_title(env, fontsize=10)
        ax.set_xlabel("env steps")
        ax.set_ylabel(f"evaluation return ({EVAL_EPISODES} episodes)")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.suptitle(command_line().replace("`", ""), fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def describe_cme(kwargs: list[str]) -> str:
    """How the report's CME runs were built, from their kwargs (JSON texts)."""
    if kwargs == ["{}"]:
        return '`CMEPolicyIteration("CMEPolicy", env_id, seed=seed)` with nothing else'
    calls = [f'`CMEPolicyIteration("CMEPolicy", env_id, seed=seed, **{text})`' for text in kwargs]
    return " or ".join(calls) + (" (runs of different kwargs mixed in one report)" if len(calls) > 1 else "")


def report(envs: list[str], steps: int, out: Path, stem: str = STEM) -> None:
    """Write <out>/<stem>.md (and .csv, .png) from the saved runs, saying which are complete.

    :param envs: the suite's envs; a held-out env is added after them where it has a saved run
    """
    runs = saved_runs(out, stem)
    envs = envs + [env for env in HELD_OUT_ENVS if any(run["job"]["env"] == env for run in runs)]
    complete: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for run in runs:
        if run["complete"]:
            complete.setdefault((run["job"]["env"], run["job"]["agent"]), []).append(run)
    header = [
        "env",
        "agent",
        "seeds",
        "steps",
        "final return (mean +- std over seeds)",
        "vs random",
        "worst seed",
        "best evaluation (mean over seeds)",
        f"steps to {TARGET_RETURN:g}",
        "train wall s/run",
        "train CPU s/run",
        "peak MiB",
        "notes",
    ]
    rows = [
        summary_row(env, agent, complete[(env, agent)], random_level(complete, env))
        for env in envs
        for agent in AGENTS
        if (env, agent) in complete
    ]
    partial_header = ["env", "agent", "seed", "steps reached", "last return", "best", "train wall s", "peak MiB", "curve"]
    partial = [partial_row(run) for run in runs if not run["complete"]]
    unfinished = [
        f"{run['job']['agent']} {run['job']['env']} seed {run['job']['seed']} "
        f"({'failed' if run.get('error') else 'stopped'} at {last_step(run)} steps)"
        for run in runs
        if not run["complete"]
    ]
    planned = [Job(agent, env, seed, steps, 0, str(out), stem=stem) for seed in (0, 1, 2) for agent in AGENTS for env in envs]
    missing = [f"{job.agent} {job.env} seed {job.seed}" for job in planned if load_record(job.path) is None]
    done = ", ".join(
        f"{agent} {env} seeds {sorted(run['job']['seed'] for run in group)}"
        for (env, agent), group in sorted(complete.items())
    )
    commands = sorted({f"`{run['job']['command']}` (runs at commit `{run['commit']}`)" for run in runs})
    cme_kwargs = sorted({run["job"].get("kwargs", "{}") for run in runs if run["job"]["agent"] == "cme"}) or ["{}"]
    text = "\n".join(
        [
            f"# Unseen envs{' at library defaults' if cme_kwargs == ['{}'] else ''}: CME vs SB3 SAC vs random",
            "",
            f"Report: `{command_line()}`. Runs made by: {'; '.join(commands) or 'none'}.",
            "",
            f"CME is {describe_cme(cme_kwargs)} (no env here has a preset); "
            'SAC is `SAC("MlpPolicy", env_id, seed=seed)` at SB3\'s defaults (learning_starts=100, buffer 1e6, batch 256, '
            "one gradient step per env step) on the CPU; random takes uniform actions, zero the action space's centre "
            "at every step (doing nothing). Final return = the last "
            f"{EVAL_EPISODES}-episode evaluation of the deterministic policy on an env seeded seed + {EVAL_SEED_OFFSET:,} "
            f"(random, zero: {RANDOM_EPISODES} episodes). 'steps to {TARGET_RETURN:g}' = first evaluation (every "
            f"{runs[0]['job']['eval_every'] if runs else '?'} steps) at or above it on {TARGET_ENV}, per seed. "
            "Train wall/CPU = seconds in learn() per run (thread CPU time; evaluations apart); peak MiB = ru_maxrss of the "
            "job's own process (torch, SB3 and MuJoCo included; what the process held before building the agent is in "
            "each run's JSON). One job at a time, one torch thread, on a 2-core machine shared with other work.",
            "",
            markdown_table(header, rows),
            "",
            "## Return by budget",
            "",
            "The evaluation return of each learning agent after 2,000, 5,000 and 10,000 env steps and at the end "
            "(mean +- std over the seeds evaluated there): a model-based agent may lead early and fall behind later.",
            "",
            *by_budget(complete, envs, steps),
            "",
            "## Targets",
            "",
            *verdicts(complete, steps),
            "",
            "## Runs",
            "",
            f"Complete: {sum(len(v) for v in complete.values())} ({done}).",
            "",
            f"Started, not complete (excluded above): {', '.join(unfinished) or 'none'}.",
            "",
            *([markdown_table(partial_header, partial), ""] if partial else []),
            f"Not run: {', '.join(missing) or 'none'}.",
            "",
        ]
    )
    print(text)
    (out / f"{stem}.md").write_text(text)
    every = [run for runs_of in complete.values() for run in runs_of]
    prefix = ("env", "agent", "seed")
    write_csv(
        out / f"{stem}.csv",
        [{k: run["job"][k] for k in prefix} | {"commit": run["commit"]} | row for run in every for row in run["evaluations"]],
    )
    plot(complete, [env for env in envs if any(key[0] == env for key in complete)] or envs, out / f"{stem}.png")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--agents", nargs="+", default=list(AGENTS), choices=AGENTS)
    parser.add_argument("--envs", nargs="+", default=[*ENVS, *REPORTED_ENVS], choices=ENVS + REPORTED_ENVS + HELD_OUT_ENVS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=20_000, help="env steps per run")
    parser.add_argument("--eval-every", type=int, default=1_000, help="env steps between evaluations")
    parser.add_argument("--workers", type=int, default=1, help="jobs at a time (each a process with one torch thread)")
    parser.add_argument("--out", type=Path, default=RESULTS, help="results folder (default results/)")
    parser.add_argument("--kwargs", default="{}", help="CME's constructor arguments beyond the env and the seed, as JSON")
    parser.add_argument("--stem", default=STEM, help="name of the report (results/<stem>.md) and of its runs' folder")
    parser.add_argument("--report-only", action="store_true", help="only write the report from the saved runs")
    args = parser.parse_args()
    try:
        kwargs = json.loads(args.kwargs)
    except json.JSONDecodeError as error:
        parser.error(f"--kwargs is not JSON: {error}")
    if not isinstance(kwargs, dict):
        parser.error(f"--kwargs must be a JSON object of constructor arguments, got {args.kwargs!r}")
    if kwargs and args.stem == STEM:
        parser.error(f"--kwargs changes CME from the defaults: give the runs a --stem other than {STEM!r}")
    if not args.report_only:
        jobs = planned_jobs(args.agents, args.envs, args.seeds, args.steps, args.eval_every, args.out, args.kwargs, args.stem)
        run_all(jobs, args.workers)
    report([*ENVS, *REPORTED_ENVS], args.steps, args.out, args.stem)


if __name__ == "__main__":
    main()
