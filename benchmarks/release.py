"""Regenerate every report of results/ at one commit, with one command.

Each step is the command that makes one group of results/ files. The steps run in order, cheapest
first, each a fresh process; a finished step is recorded in ``results/release/state.json``, so an
interrupted release continues where it stopped, and the per-run records of the benchmarks inside a
step (``results/<benchmark>/``) let a step continue too. ``results/release.md`` says which steps
were made at which commit, with their commands, outputs and seconds. A release runs from a clean checkout of one
commit, best a worktree of its own, so that the rest of the work can go on beside it::

    git worktree add .worktrees/release HEAD
    cd .worktrees/release && python -m benchmarks.release --workers 2   # many CPU-hours; rerun to continue
    python -m benchmarks.release --list                                 # the steps and their commands
    python -m benchmarks.release --export ../..                         # copy what is made into the branch

``--export DIR`` copies into ``DIR/results/`` the outputs of the steps made and ``release.md``; while
steps are left it also packs the release in progress (its state, the outputs made, the run records
and checkpoints of the steps left) into ``results/release-progress.tar.gz`` beside them, so that the release can
go on in another checkout of the branch (a fresh machine): make the worktree at the release's
commit, copy that archive into its ``results/`` and run the release again, which unpacks it.
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import subprocess
import sys
import tarfile
import time
from dataclasses import dataclass
from pathlib import Path

from benchmarks.common import RESULTS, ROOT, code_version, markdown_table, save_record

STATE = RESULTS / "release" / "state.json"
"""The steps made so far and their seconds (scratch, as every folder of results/ is)."""
REPORT = RESULTS / "release.md"
PROGRESS = RESULTS / "release-progress.tar.gz"
"""A release in progress, packed by ``--export`` to go on in another checkout (unpacked on start)."""


@dataclass(frozen=True)
class Step:
    """One group of results/ files and the commands that make them.

    :param name: what ``--only`` calls it
    :param commands: command lines, run in order from the repository root (``python`` is this interpreter)
    :param outputs: the files it writes under results/
    :param records: its per-run records and checkpoints under results/ (scratch), from which an
        interrupted step continues: what an export packs while the step is not made
    """

    name: str
    commands: tuple[str, ...]
    outputs: tuple[str, ...]
    records: tuple[str, ...] = ()


def steps(workers: int) -> list[Step]:
    """Every step of a release, cheapest first; ``workers`` runs at a time where a step trains several."""
    jobs = f"--workers {workers}"
    ten_seeds = " ".join(str(seed) for seed in range(10))
    figures = tuple(f"{stem}.{ext}" for stem in ("figure1", "figure2", "figure3") for ext in ("md", "csv", "png"))
    observation = shlex.quote('{"model_update": {"kind": "observation"}}')
    waves = shlex.quote('{"model_update": {"kind": "observation", "change_fourier": 500}}')
    return [
        Step("threads", ("python -m benchmarks.threads",), ("threads.md",)),
        Step("defaults_memory", ("python -m benchmarks.defaults_memory --repeats 3",), ("defaults_memory.md",)),
        Step(
            "iteration_cost",
            ("python -m benchmarks.iteration_cost --repeats 3 --small 25000 --large 50000",),
            ("iteration_cost.md",),
        ),
        Step(
            "interrupt_resume",
            (f"python -m benchmarks.interrupt_resume --seeds 0 1 2 3 4 --overrides total_timesteps=3000 {jobs}",),
            ("interrupt_resume.md", "interrupt_resume.csv"),
            ("interrupt_resume_runs",),
        ),
        Step(
            "learning_quality",
            (f"python -m benchmarks.learning_quality {jobs}",),
            ("learning_quality.md", "learning_quality.csv", "learning_quality.png"),
            ("learning_quality",),
        ),
        Step(
            "ip_defaults",
            (
                "python -m benchmarks.learning_quality --envs --env-id InvertedPendulum-v5 --steps 5000 --target 950 "
                f"--seeds {ten_seeds} --stem ip_defaults {jobs}",
            ),
            ("ip_defaults.md", "ip_defaults.csv", "ip_defaults.png"),
            ("ip_defaults",),
        ),
        Step(
            "paper",
            (f"python -m benchmarks.reproduce {jobs}",),
            (*figures, "sample_efficiency.md", "sample_efficiency.csv"),
            ("runs",),
        ),
        Step(
            "quadcopter_gifs",
            (
                "python train.py env=quadcopter seed=0 hydra.run.dir=results/quadcopter_seed0",
                "python -m benchmarks.quadcopter_gif --model results/quadcopter_seed0/model.zip "
                "--output results/quadcopter_cme.gif",
                "python -m benchmarks.quadcopter_gif --output results/quadcopter_scripted.gif",
            ),
            ("quadcopter_cme.gif", "quadcopter_scripted.gif"),
            ("quadcopter_seed0",),
        ),
        Step(
            "unseen_envs",
            (f"python -m benchmarks.unseen_envs --seeds 0 1 2 3 4 {jobs}",),
            ("unseen_envs.md", "unseen_envs.csv", "unseen_envs.png"),
            ("unseen_envs",),
        ),
        Step(
            "unseen_envs_auto",
            (  # the envs where the default model_update.kind="auto" chooses the model of the observation
                "python -m benchmarks.unseen_envs --agents cme --envs InvertedPendulum-v5 PointGoal2D-v0 "
                f"--seeds 0 1 2 3 4 --stem unseen_envs_auto {jobs}",
            ),
            ("unseen_envs_auto.md", "unseen_envs_auto.csv", "unseen_envs_auto.png"),
            ("unseen_envs_auto",),
        ),
        Step(
            "unseen_envs_waves",
            (  # the model of the observation with waves of (s, a) where its linear change falls short (an option)
                "python -m benchmarks.unseen_envs --agents cme --envs InvertedDoublePendulum-v5 Reacher-v5 "
                f"--kwargs {waves} --seeds 0 1 2 --stem unseen_envs_waves {jobs}",
            ),
            ("unseen_envs_waves.md", "unseen_envs_waves.csv", "unseen_envs_waves.png"),
            ("unseen_envs_waves",),
        ),
        Step(
            "unseen_envs_observation",
            (  # HalfCheetah and Hopper (about 15 minutes a run) on seed 0 only
                f"python -m benchmarks.unseen_envs --agents cme --kwargs {observation} --stem unseen_envs_observation "
                f"--seeds 0 {jobs}",
                f"python -m benchmarks.unseen_envs --agents cme --kwargs {observation} --stem unseen_envs_observation "
                f"--envs InvertedPendulum-v5 InvertedDoublePendulum-v5 Reacher-v5 PointGoal2D-v0 --seeds 0 1 2 {jobs}",
            ),
            ("unseen_envs_observation.md", "unseen_envs_observation.csv", "unseen_envs_observation.png"),
            ("unseen_envs_observation",),
        ),
        Step(
            "endurance",
            ("python -m benchmarks.endurance --steps 200000 --resume",),
            ("endurance.md", "endurance.csv", "endurance.png"),
            ("endurance_checkpoint.zip",),
        ),
    ]


def load_state(commit: str) -> dict[str, float]:
    """Seconds of each step already made at ``commit``; refuses a record of another commit."""
    if not STATE.exists():
        return {}
    state = json.loads(STATE.read_text())
    if state["commit"] != commit:
        raise SystemExit(
            f"{STATE} records a release at {state['commit']}, this checkout is {commit}: release each commit from "
            "a fresh worktree (git worktree add .worktrees/release-<commit> <commit>)"
        )
    return dict(state["steps"])


def unpack_progress() -> None:
    """Continue a release packed in another checkout: unpack ``PROGRESS`` unless a state is already here."""
    if STATE.exists() or not PROGRESS.exists():
        return
    with tarfile.open(PROGRESS) as archive:
        archive.extractall(RESULTS, filter="data")
    print(f"continuing the release packed in {PROGRESS}", flush=True)


def export(plan: list[Step], destination: Path, commit: str) -> None:
    """Copy the outputs of the steps made at ``commit`` and ``release.md`` into ``destination/results``,
    with the release packed in ``release-progress.tar.gz`` while steps are left (removed there once none are)."""
    done = load_state(commit)
    target = destination / "results"
    if not target.is_dir() or target.resolve() == RESULTS.resolve():
        raise SystemExit(f"--export needs another checkout's folder holding results/, not {destination}")
    made = [output for step in plan if step.name in done for output in step.outputs] + [REPORT.name]
    for name in made:
        shutil.copy2(RESULTS / name, target / name)
    if all(step.name in done for step in plan):
        (target / PROGRESS.name).unlink(missing_ok=True)
        print(f"release at {commit} exported to {target}: complete")
        return
    with tarfile.open(target / PROGRESS.name, "w:gz") as archive:
        left = [name for step in plan if step.name not in done for name in step.records]
        for name in [STATE.parent.name, *left, *made]:
            if (RESULTS / name).exists():
                archive.add(RESULTS / name, arcname=name)
    print(
        f"release at {commit} exported to {target}, {len(done)} of {len(plan)} steps made, the rest packed in {PROGRESS.name}"
    )


def write_report(plan: list[Step], commit: str, done: dict[str, float]) -> None:
    """results/release.md: each step made at ``commit``, its commands, outputs and hours."""
    rows = [
        ["<br>".join(f"`{command}`" for command in step.commands), ", ".join(step.outputs), f"{done[step.name] / 3600:.2f}"]
        for step in plan
        if step.name in done
    ]
    left = [step.name for step in plan if step.name not in done]
    REPORT.write_text(
        f"# Release at commit `{commit}`\n\nMade by `python -m benchmarks.release` from a clean checkout of `{commit}`: "
        f"each step's command, the files of results/ it wrote and its wall-clock hours. Steps not made yet: "
        f"{', '.join(left) or 'none'}.\n\n{markdown_table(['commands', 'outputs', 'hours'], rows)}\n"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workers", type=int, default=1, help="runs at a time inside a step (one process each)")
    parser.add_argument("--only", nargs="+", help="the steps to make (default: all)")
    parser.add_argument("--list", action="store_true", help="print the steps, their commands and outputs, run nothing")
    parser.add_argument("--export", type=Path, metavar="DIR", help="copy what is made (and the progress) into DIR/results")
    args = parser.parse_args()
    plan = steps(args.workers)
    names = [step.name for step in plan]
    unknown = sorted(set(args.only or []) - set(names))
    if unknown:
        parser.error(f"unknown steps {unknown}; the steps are {names}")
    selected = [step for step in plan if args.only is None or step.name in args.only]
    if args.list:
        for step in selected:
            print(f"{step.name}: {'; '.join(step.commands)}\n    -> {', '.join(step.outputs)}")
        return
    commit = code_version()
    if commit.endswith("+changes") or commit == "unknown":
        raise SystemExit(f"the code is at {commit}: a release runs from a clean checkout of one commit")
    if args.export:
        export(plan, args.export, commit)
        return
    unpack_progress()
    done = load_state(commit)
    for step in selected:
        if step.name in done:
            print(f"{step.name}: made at {commit} ({done[step.name]:.0f} s)", flush=True)
            continue
        start, started = time.perf_counter(), time.time()
        for command in step.commands:
            print(f"{step.name}: {command}", flush=True)
            subprocess.run([sys.executable, *shlex.split(command)[1:]], cwd=ROOT, check=True)
        stale = [name for name in step.outputs if not (RESULTS / name).exists() or (RESULTS / name).stat().st_mtime < started]
        if stale:
            raise SystemExit(f"{step.name} did not write {stale}")
        done[step.name] = time.perf_counter() - start
        save_record(STATE, {"commit": commit, "steps": done})
        write_report(plan, commit, done)
    left = [name for name in names if name not in done]
    print(f"release at {commit}: {len(done)} of {len(names)} steps made" + (f"; left: {left}" if left else ""))


if __name__ == "__main__":
    main()
