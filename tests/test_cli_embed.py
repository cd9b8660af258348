"""Tests of the ``don-gym embed`` command."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
import trimesh

from don_gym.cli import main
from don_gym.descriptors import DescriptorField


def one_error_line(stderr: str, *fragments: str) -> str:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("don-gym embed: error: ") and "Traceback" not in stderr
    for fragment in fragments:
        assert fragment in lines[0]
    return lines[0]


def test_embed_toolcap_writes_field_and_picture(tmp_path, capsys):
    out, picture = tmp_path / "field.npz", tmp_path / "pictures" / "toolcap.png"
    assert main(["embed", "toolcap", "--out", str(out), "--plot", str(picture)]) == 0
    stdout = capsys.readouterr().out
    assert "4226 vertices" in stdout
    assert "d1 = eigenvector 1; d2 = eigenvector 2; d3 = sum of squares 3+4" in stdout
    field = DescriptorField.load(out)
    assert f"field hash:  {field.field_hash}" in stdout
    assert f"background:  [{', '.join(f'{v:.3f}' for v in field.background)}]" in stdout
    assert f"wrote {out}" in stdout and f"wrote {picture}" in stdout
    image = matplotlib.image.imread(picture)
    assert image.shape[0] > 300 and image.shape[1] > 800
    # Hot colour map and RGB composite: many distinct colours, not a blank figure.
    colours = np.unique((image[..., :3] * 255).astype(np.uint8).reshape(-1, 3), axis=0)
    assert len(colours) > 500


def test_embed_options_no_symmetry_and_dim(capsys):
    assert main(["embed", "shaft", "--no-symmetry", "--dim", "2", "--method", "direct"]) == 0
    stdout = capsys.readouterr().out
    assert "d1 = eigenvector 1; d2 = eigenvector 2 (no symmetry merging)" in stdout
    assert "solver direct" in stdout


def test_embed_user_errors_print_one_line(tmp_path, capsys):
    assert main(["embed", str(tmp_path / "missing.stl")]) == 2
    one_error_line(capsys.readouterr().err, "missing.stl", "does not exist")

    two = trimesh.util.concatenate(
        [trimesh.creation.icosphere(2, radius=0.02), trimesh.creation.box((0.01, 0.01, 0.01))]
    )
    two.vertices[len(two.vertices) - 8 :] += [0.1, 0.0, 0.0]
    pieces = tmp_path / "pieces.ply"
    two.export(pieces)
    assert main(["embed", str(pieces)]) == 2
    one_error_line(capsys.readouterr().err, "2 connected components", "largest")
    assert main(["embed", str(pieces), "--components", "largest", "--no-symmetry"]) == 0
    assert "embedded the largest component: 162 vertices" in capsys.readouterr().out

    assert main(["embed", "toolcap", "--out", str(tmp_path / "field.txt")]) == 2
    one_error_line(capsys.readouterr().err, ".npz")
    assert main(["embed", "toolcap", "--plot", str(tmp_path / "picture.bmpx")]) == 2
    one_error_line(capsys.readouterr().err, ".png")
    assert main(["embed", "toolcap", "--dim", "0"]) == 2
    one_error_line(capsys.readouterr().err, "dim=0")
    assert main(["embed", "toolcap", "--scale", "-2"]) == 2
    one_error_line(capsys.readouterr().err, "scale")


def test_embed_help_explains_the_options(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["embed", "--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    for option in ("--dim", "--no-symmetry", "--scale", "--out", "--plot", "--components", "--tolerance", "hot"):
        assert option in text


def test_console_script_reports_a_bad_file_in_one_line(tmp_path):
    script = Path(sys.executable).parent / "don-gym"
    if not script.exists():
        script = Path(shutil.which("don-gym") or "don-gym")
    assert script.exists(), "the don-gym console script is not installed (pip install -e .)"
    broken = tmp_path / "broken.obj"
    broken.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    result = subprocess.run([str(script), "embed", str(broken)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    one_error_line(result.stderr, "broken.obj", "NaN")
    assert result.stdout == ""
