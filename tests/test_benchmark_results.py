"""Every RESULTS.md section names the commit it was measured on, and whether the code differed from it."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import _results  # noqa: E402


@pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")
def test_section_records_the_commit_and_uncommitted_changes(tmp_path: Path, monkeypatch) -> None:
    def git(*args: str) -> str:
        command = ["git", "-c", "user.email=t@example.com", "-c", "user.name=t", *args]
        return subprocess.run(command, cwd=tmp_path, check=True, capture_output=True, text=True).stdout

    git("init", "-q")
    (tmp_path / "benchmarks" / "figures").mkdir(parents=True)
    for name in ("code.py", "benchmarks/RESULTS.md", "benchmarks/figures/a.png"):
        (tmp_path / name).write_text("1")
    git("add", "-A")
    git("commit", "-qm", "first")
    commit = git("rev-parse", "--short", "HEAD").strip()
    monkeypatch.setattr(_results, "REPO_ROOT", tmp_path)

    # The benchmarks' own outputs and untracked files do not make the code uncommitted ...
    (tmp_path / "benchmarks/figures/a.png").write_text("2")
    (tmp_path / "new.py").write_text("untracked")
    section = _results.record_section("x", "X", "body", path=tmp_path / "benchmarks" / "RESULTS.md")
    assert f"- Commit: {commit}\n" in section
    # ... an edited or renamed tracked file does.
    git("mv", "code.py", "moved.py")
    assert _results.commit_description() == f"{commit} + uncommitted changes"

    monkeypatch.setenv("PATH", str(tmp_path / "no-bin"))  # no git at all
    assert _results.commit_description() == "unknown"
