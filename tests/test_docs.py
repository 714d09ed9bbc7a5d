"""The documentation builds with warnings as errors (MkDocs + mkdocstrings, API pages from the
docstrings), and the README's links into it hold."""

import os
import re
import subprocess
import sys

import pytest

from tests.conftest import ROOT


def test_mkdocs_build_strict(tmp_path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings")
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    assert result.returncode == 0, result.stderr[-5000:]
    api = (tmp_path / "site" / "api" / "agents" / "index.html").read_text()
    assert "CMEPolicyIteration" in api and "steps_per_iteration" in api  # rendered from the docstrings
    assert (tmp_path / "site" / "results" / "figure1.png").exists()  # the figures the pages show
    # docs/results.md and results/README.md both want results/index.html: the Results page keeps it
    assert 'id="cartpole-soft-planner"' in (tmp_path / "site" / "results" / "index.html").read_text()
    assert (tmp_path / "site" / "results" / "README" / "index.html").exists()


def test_readme_links_exist():
    readme = (ROOT / "README.md").read_text()
    targets = re.findall(r"\]\(((?:docs|results)/[^)#]+)", readme)
    assert targets, "the README links its documentation"
    missing = [target for target in targets if not (ROOT / target).exists()]
    assert not missing


def test_readme_test_command_is_ci_s():
    """The README's test command runs what CI runs (the last line of .ci/run), character for character."""
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()[-1]
    readme = (ROOT / "README.md").read_text()
    commands = [line for line in readme.splitlines() if line.startswith("python3 -m venv .venv")]
    assert any(line.endswith(" && " + ci) for line in commands), ci
