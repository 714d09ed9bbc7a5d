"""Helpers shared by the benchmark scripts: composing the Hydra configs, writing results."""

from __future__ import annotations

import csv
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results"


def compose_config(overrides: list[str]) -> DictConfig:
    """The config ``python train.py <overrides>`` would run with."""
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        return compose(config_name="config", overrides=overrides)


def command_line() -> str:
    """The command that is running, as a user would type it from the repository root, and the
    commit of the code it ran (with ``+changes`` if the work tree differed from it)."""
    script = Path(sys.argv[0]).resolve().relative_to(ROOT)
    command = " ".join(["python", str(script), *(shlex.quote(a) for a in sys.argv[1:])])
    return f"{command}` at commit `{code_version()}"


def code_version() -> str:
    """``git describe``-like id of the code: the short commit hash, ``+changes`` if the tree is dirty."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True)
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True, text=True
        )
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return commit.stdout.strip() + ("+changes" if dirty.stdout.strip() else "")


def markdown_table(header: list[str], rows: list[list[Any]]) -> str:
    """A GitHub-flavoured markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def write_report(stem: str, text: str, curves: list[list[dict[str, Any]]]) -> None:
    """Print ``text`` and write it to results/<stem>.md, the learning curves (one row per
    evaluation, all runs) to results/<stem>.csv."""
    print(text)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{stem}.md").write_text(text)
    with open(RESULTS / f"{stem}.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(curves[0][0]))
        writer.writeheader()
        for curve in curves:
            writer.writerows(curve)
