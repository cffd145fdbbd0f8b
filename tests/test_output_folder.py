"""An output folder holding another run's results is refused unless ``--overwrite`` (issue 33, item 6).

Before, ``optimize`` rerun into the same folder with other settings overwrote result.json, history.csv and
the checkpoint and left the old task's TOML beside the new one; ``study`` rerun with other placements
replaced study.csv with a table of the new placements only.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from place3d_app.cli import main

TINY = ["--frames", "8", "--voxel-size", "0.8", "--quiet", "--backend", "warp:cpu"]


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "cache"))


def _one_error(capsys) -> str:
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("place3d")]
    assert len(lines) == 1, lines
    return lines[0]


def test_optimize_into_a_folder_of_another_run(capsys):
    base = ["optimize", *TINY, "--max-evals", "10", "--interval", "none", "--output", "o"]
    assert main(base) == 0
    before = Path("o/result.json").read_text()
    assert main(base) == 0                                     # the same settings: a rerun, allowed
    capsys.readouterr()
    assert main(base + ["--task", "det"]) == 2
    msg = _one_error(capsys)
    assert "result.json" in msg and "task" in msg and "--overwrite" in msg
    assert json.loads(Path("o/result.json").read_text())["task"] == "seg"
    assert Path("o/optimized-seg.toml").exists() and not Path("o/optimized-det.toml").exists()
    assert json.loads(Path("o/result.json").read_text())["setup"] == json.loads(before)["setup"]
    assert main(base + ["--task", "det", "--resume", "--overwrite"]) == 2
    assert "--overwrite" in _one_error(capsys)
    assert main(base + ["--task", "det", "--overwrite"]) == 0
    assert json.loads(Path("o/result.json").read_text())["task"] == "det"
    assert Path("o/optimized-det.toml").exists() and not Path("o/optimized-seg.toml").exists()


def test_optimize_refuses_the_checkpoint_of_another_run_without_results(capsys):
    """A run killed before its results leaves a checkpoint; another run there is refused, not started over."""
    base = ["optimize", *TINY, "--max-evals", "10", "--interval", "none", "--output", "o"]
    assert main(base) == 0
    Path("o/result.json").unlink()
    capsys.readouterr()
    assert main(base + ["--min-distance", "0.3"]) == 2
    msg = _one_error(capsys)
    assert "checkpoint" in msg and "min_distance" in msg


def _study(path: Path, placements) -> Path:
    pl = ", ".join(f'"{p}"' for p in placements)
    path.write_text(f'[study]\nname = "t"\nvoxel_size = 0.8\nresamples = 0\nplacements = [{pl}]\n'
                    f'[[scenes]]\nname = "town"\nseed = 0\nframes = 8\n[[conditions]]\nname = "clean"\n')
    return path


def test_study_rerun_with_other_placements(tmp_path, capsys):
    a = _study(tmp_path / "a.toml", ["center"])
    assert main(["study", str(a), "--output", "st", "--quiet", "--backend", "warp:cpu"]) == 0
    table = Path("st/study.csv").read_text()
    assert main(["study", str(a), "--output", "st", "--quiet", "--backend", "warp:cpu"]) == 0   # rerun
    capsys.readouterr()
    b = _study(tmp_path / "b.toml", ["center", "line"])
    assert main(["study", str(b), "--output", "st", "--quiet", "--backend", "warp:cpu"]) == 2
    msg = _one_error(capsys)
    assert "study.json" in msg and "placements" in msg and "--overwrite" in msg
    assert Path("st/study.csv").read_text() == table
    assert main(["study", str(b), "--output", "st", "--quiet", "--backend", "warp:cpu", "--overwrite"]) == 0
    assert len(Path("st/study.csv").read_text().splitlines()) == 3
