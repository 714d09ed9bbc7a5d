"""benchmarks/release.py: steps run once per commit, resume after an interruption, and refuse a
dirty checkout, another commit's record and a step that did not write its outputs."""

from __future__ import annotations

import importlib.util
import shlex
import sys
import tarfile
from pathlib import Path

import pytest

from benchmarks import release
from benchmarks.common import ROOT


@pytest.fixture
def results(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setattr(release, "RESULTS", tmp_path)
    monkeypatch.setattr(release, "STATE", tmp_path / "release" / "state.json")
    monkeypatch.setattr(release, "REPORT", tmp_path / "release.md")
    monkeypatch.setattr(release, "PROGRESS", tmp_path / "release-progress.tar.gz")
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
        assert step.outputs and all("/" not in name for name in (*step.outputs, *step.records))
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


def test_an_exported_release_goes_on_in_another_checkout(results: Path, tmp_path_factory, monkeypatch) -> None:
    records = results / "bench" / "runs"
    plan = [
        release.Step("first", (writing(results / "a.md"), writing(results / "first.json")), ("a.md",), ("first.json",)),
        release.Step(
            "second",
            (
                shlex.join(["python", "-c", f"import os; os.makedirs({str(records)!r})"]),
                writing(records / "seed0.json", "record"),
                "python -c 'raise SystemExit(3)'",
            ),
            ("b.md",),
            ("bench",),
        ),
    ]
    monkeypatch.setattr(release, "steps", lambda workers: plan)
    with pytest.raises(Exception, match="3"):  # interrupted inside the second step, one of its records made
        run_main(monkeypatch)
    branch = tmp_path_factory.mktemp("branch")
    with pytest.raises(SystemExit, match="another checkout"):
        run_main(monkeypatch, "--export", str(branch))  # no results/ there
    (branch / "results").mkdir()
    run_main(monkeypatch, "--export", str(branch))
    assert (branch / "results" / "a.md").read_text() == "made"
    assert "Steps not made yet: second" in (branch / "results" / "release.md").read_text()
    assert not (branch / "results" / "b.md").exists()

    fresh = tmp_path_factory.mktemp("fresh")  # another checkout at the same commit, the archive copied in
    monkeypatch.setattr(release, "RESULTS", fresh)
    monkeypatch.setattr(release, "STATE", fresh / "release" / "state.json")
    monkeypatch.setattr(release, "REPORT", fresh / "release.md")
    monkeypatch.setattr(release, "PROGRESS", fresh / "release-progress.tar.gz")
    (fresh / "release-progress.tar.gz").write_bytes((branch / "results" / "release-progress.tar.gz").read_bytes())
    carried = fresh / "bench" / "runs" / "seed0.json"
    with tarfile.open(fresh / "release-progress.tar.gz") as archive:
        assert "first.json" not in archive.getnames()  # a made step's records stay behind
    plan[:] = [
        release.Step("first", ("python -c 'raise SystemExit(4)'",), ("a.md",)),  # made already: not run again
        release.Step(
            "second",
            (shlex.join(["python", "-c", f"assert open({str(carried)!r}).read() == 'record'"]), writing(fresh / "b.md")),
            ("b.md",),
        ),
    ]
    run_main(monkeypatch)
    assert (fresh / "b.md").read_text() == "made"
    (branch / "results" / "a.md").write_text("stale")  # the branch gets every output again, the first's as made
    run_main(monkeypatch, "--export", str(branch))
    assert (branch / "results" / "b.md").read_text() == "made"
    assert (branch / "results" / "a.md").read_text() == "made"
    assert not (branch / "results" / "release-progress.tar.gz").exists()  # complete: nothing left to carry


def test_unknown_step_names_are_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(SystemExit):
        run_main(monkeypatch, "--only", "figure9", "--list")
