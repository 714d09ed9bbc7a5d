"""benchmarks/release.py: steps run once per commit, resume after an interruption, and refuse a
dirty checkout, another commit's record and a step that did not write its outputs."""

from __future__ import annotations

import importlib.util
import shlex
import sys
from pathlib import Path

import pytest

from benchmarks import release
from benchmarks.common import ROOT


@pytest.fixture
def results(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setattr(release, "RESULTS", tmp_path)
    monkeypatch.setattr(release, "STATE", tmp_path / "release" / "state.json")
    monkeypatch.setattr(release, "REPORT", tmp_path / "release.md")
    monkeypatch.setattr(release, "code_version", lambda: "abc1234")
    return tmp_path


def writing(path: Path, text: str = "made") -> str:
    """A command line that writes ``text`` to ``path``."""
    return shlex.join(["python", "-c", f"open({str(path)!r}, 'w').write({text!r})"])


def run_main(monkeypatch: pytest.MonkeyPatch, *arguments: str) -> None:
    monkeypatch.setattr(sys, "argv", ["release.py", *arguments])
    release.main()


def test_every_step_runs_a_module_or_script_of_the_repository() -> None:
    for step in release.steps(workers=2):
        for command in step.commands:
            words = shlex.split(command)
            assert words[0] == "python"
            if words[1] == "-m":
                assert importlib.util.find_spec(words[2]) is not None, command
            else:
                assert (ROOT / words[1]).is_file(), command
        assert step.outputs and all("/" not in name for name in step.outputs)
    names = [step.name for step in release.steps(workers=1)]
    assert len(names) == len(set(names))


def test_steps_run_once_and_a_rerun_continues_after_the_last_made(results: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    plan = [
        release.Step("first", (writing(results / "a.md"),), ("a.md",)),
        release.Step("second", (writing(results / "b.md"), "python -c 'raise SystemExit(3)'"), ("b.md",)),
    ]
    monkeypatch.setattr(release, "steps", lambda workers: plan)
    with pytest.raises(Exception, match="3"):  # the second step fails: the first stays made
        run_main(monkeypatch)
    assert "Steps not made yet: second" in (results / "release.md").read_text()
    (results / "a.md").write_text("kept")
    plan[1] = release.Step("second", (writing(results / "b.md"),), ("b.md",))
    run_main(monkeypatch)
    assert (results / "a.md").read_text() == "kept"  # not made again
    assert (results / "b.md").read_text() == "made"
    report = (results / "release.md").read_text()
    assert "`abc1234`" in report and "Steps not made yet: none" in report and "a.md" in report and "b.md" in report


def test_a_step_that_leaves_its_outputs_stale_fails(results: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (results / "old.md").write_text("from an older commit")
    plan = [release.Step("quiet", ("python -c pass",), ("old.md",))]
    monkeypatch.setattr(release, "steps", lambda workers: plan)
    with pytest.raises(SystemExit, match=r"did not write \['old.md'\]"):
        run_main(monkeypatch)


def test_a_dirty_checkout_and_another_commits_record_are_refused(results: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    plan = [release.Step("first", (writing(results / "a.md"),), ("a.md",))]
    monkeypatch.setattr(release, "steps", lambda workers: plan)
    run_main(monkeypatch)
    monkeypatch.setattr(release, "code_version", lambda: "def5678")
    with pytest.raises(SystemExit, match="records a release at abc1234"):
        run_main(monkeypatch)
    monkeypatch.setattr(release, "code_version", lambda: "abc1234+changes")
    with pytest.raises(SystemExit, match="clean checkout"):
        run_main(monkeypatch)


def test_unknown_step_names_are_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(SystemExit):
        run_main(monkeypatch, "--only", "figure9", "--list")
