"""A drive of fewer than 3 subsets gets no interval, and says so (issue 33, item 6, "Silently wrong").

Before, ``evaluate --routes 1 --frames 8`` (T = 2 subsets of k = 4 frames) printed intervals of zero width
and "within noise: none": leaving one of two subsets out pools a single subset, whose every voxel holds one
class, so every rescored M-SOG was 0 and the jackknife's standard error 0.
"""

from __future__ import annotations

import json
import re

import pytest

from place3d_app.cli import main

TINY = ["--voxel-size", "0.8", "--routes", "1", "--quiet", "--backend", "warp:cpu"]
NOTE = "intervals need at least 3 subsets; this drive has 2"


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "cache"))


@pytest.mark.parametrize("interval", [["--interval", "jackknife"], ["--interval", "bootstrap", "--resamples", "8"]])
def test_evaluate_with_two_subsets_has_no_interval_columns(capsys, interval):
    assert main(["evaluate", *TINY, "--frames", "8", *interval, "center", "line", "--output", "r.json"]) == 0
    cap = capsys.readouterr()
    notes = [ln for ln in cap.err.splitlines() if NOTE in ln]
    assert len(notes) == 1 and notes[0].startswith("place3d: note: ") and "12 frames" in notes[0], cap.err
    assert "interval" not in cap.out and "within noise" not in cap.out and "[" not in cap.out, cap.out
    out = json.loads(open("r.json").read())
    assert "bootstrap" not in out and NOTE in out["intervals_note"]
    assert "ci" not in out["rows"][0]


def test_evaluate_with_three_subsets_has_intervals_of_some_width(capsys):
    assert main(["evaluate", *TINY, "--frames", "12", "center", "line"]) == 0
    cap = capsys.readouterr()
    assert NOTE[:30] not in cap.err
    widths = [float(hi) - float(lo) for lo, hi in re.findall(r"\[\s*(-?[\d.]+),\s*(-?[\d.]+)\]", cap.out)]
    assert len(widths) == 4 and all(w > 0 for w in widths), cap.out


def test_optimize_with_two_subsets_reports_no_interval(capsys):
    assert main(["optimize", *TINY, "--frames", "8", "--max-evals", "10", "--interval", "jackknife"]) == 0
    out = capsys.readouterr().out
    assert f"no intervals: {NOTE}" in out and "95 % intervals" not in out, out
