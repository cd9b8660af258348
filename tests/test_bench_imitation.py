"""benchmarks/bench_imitation.py's choice of inputs: a subset keeps the comparison's order, and bad input is one
line (the comparison itself runs in tests/test_imitation.py)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_imitation  # noqa: E402


def test_every_input_of_the_comparison_for_a_part():
    inputs = bench_imitation.all_inputs("shaft")
    assert inputs[:3] == ["state", "true", "simulated:shaft/supervised-edge"]
    assert {f"don:shaft/{network}" for network in bench_imitation.NETWORKS} <= set(inputs)
    assert inputs[-2:] == ["rgbd", "descriptors:shaft/supervised-edge"]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--inputs", "state", "don:toolcap/nonsense"], "expected some of"),
        (["--inputs", "state", "--quick"], "not with --quick"),
        (["--record-as", "descriptors"], "expected imitation or imitation-"),
    ],
)
def test_bad_inputs_are_refused_in_one_line_before_anything_runs(capsys, args, message):
    with pytest.raises(SystemExit) as exit_info:
        bench_imitation.main(args)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err and "Traceback" not in err


def test_a_missing_demonstrations_file_is_one_line_without_a_traceback(tmp_path):
    import subprocess

    script = Path(bench_imitation.__file__)
    command = [sys.executable, str(script), "--parts", "comparison", "--inputs", "state",
               "--demos-file", str(tmp_path / "none.hdf5"), "--work", str(tmp_path / "work")]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode != 0
    err = done.stderr.strip()
    assert len(err.splitlines()) == 1 and "none.hdf5" in err and "no such file" in err, err


@pytest.mark.parametrize("readme_has_block", [True, False])
def test_record_as_puts_the_comparison_in_its_own_section_figure_and_readme_block(
    monkeypatch, tmp_path, readme_has_block
):
    class Result:  # what run_imitation returns, for the recording's routing only
        wins = {"state": {50: 80}, "descriptors:toolcap/supervised-edge": {50: 60}}

        def rates(self):
            return {}

        def table(self):
            return "| input | N = 50 |"

    recorded, readme, figures = [], [], []
    monkeypatch.setattr(bench_imitation, "run_imitation", lambda *args, **kwargs: Result())
    monkeypatch.setattr(
        bench_imitation, "plot_success_against_demonstrations", lambda r, path, **k: figures.append(path)
    )
    monkeypatch.setattr(bench_imitation, "record_section", lambda name, title, body, after=None: recorded.append(
        (name, title, body, after)))  # fmt: skip
    monkeypatch.setattr(bench_imitation, "replace_block", lambda path, name, text: readme.append(name))
    fake_readme = tmp_path / "README.md"
    block = "<!-- begin imitation-descriptors -->\n<!-- end imitation-descriptors -->\n" if readme_has_block else ""
    fake_readme.write_text("<!-- begin imitation -->\n<!-- end imitation -->\n" + block)
    monkeypatch.setattr(bench_imitation, "README", fake_readme)
    bench_imitation.main(["--parts", "comparison", "--inputs", "state", "descriptors:toolcap/supervised-edge",
                          "--record-as", "imitation-descriptors", "--work", str(tmp_path), "--jobs", "1"])  # fmt: skip
    ((name, title, body, after),) = recorded
    assert (name, after) == ("imitation-descriptors", "imitation") and "descriptors:toolcap/supervised-edge" in title
    assert figures == [bench_imitation.FIGURES / "imitation-descriptors.png"]
    assert readme == (["imitation-descriptors"] if readme_has_block else [])  # never the main comparison's block
    # The target line compares the supervised DON keypoints with the state: neither verdict without them.
    assert "the section `imitation` has the others" in body and "Target:" not in body
