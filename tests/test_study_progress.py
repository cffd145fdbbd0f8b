"""``place3d study`` shows its progress (issue 33, item 6: the example study printed nothing for 20 minutes).

Before, a study printed one line ("N cells, M to run") and then nothing until its table: no bar for the
P-SOGs it simulated nor for the cells it scored.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from place3d_app.cli import main


@pytest.fixture
def config(tmp_path, monkeypatch) -> Path:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "cache"))
    path = tmp_path / "s.toml"
    path.write_text('[study]\nname = "t"\nvoxel_size = 0.8\nresamples = 0\nplacements = ["center", "line", "square"]\n'
                    '[[scenes]]\nname = "town"\nseed = 0\nframes = 8\n[[conditions]]\nname = "clean"\n')
    return path


def test_study_shows_a_bar_for_its_psogs_and_cells(config, capsys):
    assert main(["study", str(config), "--output", "st", "--backend", "warp:cpu"]) == 0
    err = capsys.readouterr().err
    assert "study: P-SOGs" in err and "1/1" in err
    assert "study: cells" in err and "3/3" in err
    assert "simulate" in err                                   # the frames of the P-SOG, as they are cast


def test_quiet_study_shows_none(config, capsys):
    assert main(["study", str(config), "--output", "st", "--backend", "warp:cpu", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "study:" not in err and "simulate" not in err


def test_a_study_of_too_few_subsets_has_no_intervals_and_says_why_once(config, capsys):
    # 8 frames at k = 4 are 2 subsets: an interval over them would have zero width (intervals.MIN_SUBSETS)
    assert main(["study", str(config), "--output", "st", "--backend", "warp:cpu", "--quiet", "--resamples", "50"]) == 0
    cap = capsys.readouterr()
    warnings = [ln for ln in cap.err.splitlines() if "no intervals" in ln]
    assert len(warnings) == 1, cap.err
    assert warnings[0].startswith("place3d: warning: no intervals: scene town seed 0: intervals need at least 3 "
                                  "subsets; this drive has 2 (8 frames, k = 4); give every scene at least 12 frames")
    assert "95 % interval" not in cap.out and "square" in cap.out            # the table, without interval columns
    import json

    assert json.loads(Path("st/study.json").read_text())["settings"]["resamples"] == 0
