"""Uncertainty on every answer: bootstrap intervals and pairwise orders in evaluate, study and the
optimize helper (issue 13, item 3). Tiny settings (0.8 m voxels, a few frames) keep each test short."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from place3d_app.cli import main
from place3d_kernels.lidar import LidarModel
from place3d_kernels.placement import Placement
from place3d_kernels.spec import PSOGSpec, RoiSpec, SceneSpec
from place3d_kernels.subset_records import spec_subset_records
from place3d_kernels.uncertainty import NOISE_LEVEL, bootstrap_records, pairwise, rig_vs_baselines_intervals

#: 16 frames at k = 4: T = 4 subsets, so resamples differ (35 distinct pools) and intervals are not trivial
TINY = ["--frames", "16", "--voxel-size", "0.8", "--quiet", "--routes", "1"]
NAMES = ["center", "line", "pyramid", "square"]


def _spec() -> PSOGSpec:
    return PSOGSpec(SceneSpec("town", 0, 16), None, RoiSpec(0.8)).resolved()


# ------------------------------------------------------------------ (a) --resamples 0 is today's output
def test_resamples_zero_prints_todays_table_and_same_scores(tmp_path, capsys):
    from place3d_kernels.metrics import msog_batch

    assert main(["evaluate", *TINY, *NAMES, "--resamples", "0", "--output", str(tmp_path / "off.json")]) == 0
    off_out = capsys.readouterr().out
    assert main(["evaluate", *TINY, *NAMES, "--resamples", "30", "--output", str(tmp_path / "on.json")]) == 0
    capsys.readouterr()
    off = json.loads((tmp_path / "off.json").read_text())
    on = json.loads((tmp_path / "on.json").read_text())
    # point estimates: bit-identical with and without the bootstrap, and equal to a direct msog_batch
    assert [(r["placement"], r["msog_seg"], r["msog_det"]) for r in off["rows"]] == \
           [(r["placement"], r["msog_seg"], r["msog_det"]) for r in on["rows"]]
    psog = _spec().build()
    lidar = LidarModel.load("place3d_16ch")
    for r in off["rows"]:
        poses = Placement.load(r["placement"]).poses[None]
        assert r["msog_seg"] == float(msog_batch(psog, lidar, poses, "sog", "seg")[0])
        assert r["msog_det"] == float(msog_batch(psog, lidar, poses, "sog", "det")[0])
    # --resamples 0: no bootstrap keys, and the table in exactly the format it had before intervals
    assert "bootstrap" not in off and all(set(r) == {"placement", "msog_seg", "msog_det"} for r in off["rows"])
    assert not (tmp_path / "off.png").exists()
    lines = off_out.splitlines()
    assert lines[1] == f"{'rank':>4}  {'placement':14s} {'M-SOG seg':>12s} {'M-SOG det':>12s}"
    det_rank = {r["placement"]: i + 1 for i, r in enumerate(sorted(off["rows"], key=lambda r: -r["msog_det"]))}
    assert lines[2:2 + len(NAMES)] == [
        f"{i + 1:>4}  {r['placement']:14s} {r['msog_seg']:12.6f} {r['msog_det']:12.6f}   (det rank "
        f"{det_rank[r['placement']]})" for i, r in enumerate(off["rows"])]
    assert len(lines) == 2 + len(NAMES) + 1 and lines[-1].endswith(" s")


# ------------------------------------------------------------------ (b) ci and pairwise in eval.json
def test_eval_json_intervals_and_pairwise_match_the_resamples(tmp_path, capsys):
    out = tmp_path / "eval.json"
    assert main(["evaluate", *TINY, *NAMES, "--interval", "bootstrap", "--resamples", "40", "--resample-seed", "3",
                 "--output", str(out)]) == 0
    printed = capsys.readouterr().out
    d = json.loads(out.read_text())
    rows, bs = d["rows"], d["bootstrap"]
    assert bs["unit"] == "subsets" and bs["n_units"] == 4 and bs["n_resamples"] == 40 and bs["seed"] == 3
    # the same resamples rebuilt here: intervals and P(A > B) are what the samples say
    recs = spec_subset_records(_spec())
    order = [r["placement"] for r in rows]
    boots = bootstrap_records(recs, _spec().grid.grid(), "place3d_16ch", {n: Placement.load(n) for n in order},
                              ("seg", "det"), "sog", 40, 3)
    for task in ("seg", "det"):
        b = boots[task]
        s = b.samples
        for i, r in enumerate(rows):
            assert r["ci"][task] == b.ci[i].tolist()
            assert r["ci"][task][0] <= r["ci"][task][1]
            for j, other in enumerate(order):
                if i == j:
                    continue
                p_ab, p_ba = r["pairwise"][task][other], rows[j]["pairwise"][task][r["placement"]]
                assert p_ab + p_ba <= 1.0 + 1e-9
                want = np.mean(s[:, i] > s[:, j]) + 0.5 * np.mean(s[:, i] == s[:, j])
                assert p_ab == pytest.approx(want, abs=5e-5)
        # the within-noise list is exactly the pairs (ahead on the point, behind) whose order holds in < 95 %
        pw = {r["placement"]: r["pairwise"][task] for r in rows}
        pt = {r["placement"]: r[f"msog_{task}"] for r in rows}
        for hi, lo, p in bs["within_noise"][task]:
            assert pt[hi] >= pt[lo] and p < NOISE_LEVEL and pw[hi][lo] == pytest.approx(p, abs=5e-5)
        n_noisy = sum(1 for i, a in enumerate(order) for c in order[i + 1:]
                      if pw[max(a, c, key=pt.get)][min(a, c, key=pt.get)] < NOISE_LEVEL)
        assert len(bs["within_noise"][task]) == n_noisy
    # '~' marks exactly the adjacent seg pairs within noise; the plot exists next to --output
    table = [ln for ln in printed.splitlines() if ln[3:7].strip().isdigit()]
    assert len(table) == len(NAMES)
    for i in range(1, len(rows)):
        p = rows[i - 1]["pairwise"]["seg"][rows[i]["placement"]]
        assert (table[i][0] == "~") == (p < NOISE_LEVEL), (table[i], p)
    assert (tmp_path / "eval.png").stat().st_size > 10_000


def test_plot_path_and_bad_resamples(tmp_path, capsys):
    png = tmp_path / "scores.png"
    assert main(["evaluate", *TINY, "center", "line", "--resamples", "10", "--plot", str(png)]) == 0
    assert png.stat().st_size > 10_000
    assert main(["evaluate", *TINY, "center", "--resamples", "-1"]) == 2
    assert "--resamples" in capsys.readouterr().err


# ------------------------------------------------------------------ (c) identical placements tie
def test_identical_placements_are_within_noise():
    pl = Placement.load("pyramid")
    recs = spec_subset_records(_spec())
    boots = bootstrap_records(recs, _spec().grid.grid(), "place3d_16ch",
                              {"a": pl.poses, "b": pl.poses.copy(), "c": Placement.load("center")}, ("seg",),
                              n_resamples=25)
    b = boots["seg"]
    assert np.array_equal(b.samples[:, 0], b.samples[:, 1])
    assert b.order_freq[0, 1] == 0.5 and b.order_freq[1, 0] == 0.5
    assert pairwise(b)["a"]["b"] == 0.5
    assert any({x, y} == {"a", "b"} and p == 0.5 for x, y, p in b.within_noise())


# ------------------------------------------------------------------ (d) the optimize helper
def test_rig_vs_baselines_intervals_keys():
    base = {n: Placement.load(n) for n in ("center", "line")}
    res = rig_vs_baselines_intervals(_spec(), "place3d_16ch", Placement.load("pyramid").poses, base, task="seg",
                                     n_resamples=20, seed=1, best_name="optimised")
    assert set(res) == {"task", "method", "level", "unit", "n_units", "n_resamples", "best", "baselines"}
    assert res["unit"] == "subsets" and res["n_units"] == 4 and res["n_resamples"] == 20
    assert set(res["best"]) == {"name", "score", "ci"} and res["best"]["name"] == "optimised"
    assert [r["name"] for r in res["baselines"]] == ["center", "line"]
    for r in res["baselines"]:
        assert set(r) == {"name", "score", "ci", "p_best_better", "within_noise"}
        assert 0.0 <= r["p_best_better"] <= 1.0 and r["ci"][0] <= r["ci"][1]
        assert r["within_noise"] == (r["p_best_better"] < NOISE_LEVEL)
    # a "best" rig identical to a baseline beats it in exactly half of the resamples (all ties)
    same = rig_vs_baselines_intervals(_spec(), "place3d_16ch", base["line"].poses, base, n_resamples=10)
    tie = same["baselines"][1]
    assert tie["p_best_better"] == 0.5 and tie["within_noise"] and tie["score"] == same["best"]["score"]
    with pytest.raises(ValueError, match="best_poses"):
        rig_vs_baselines_intervals(_spec(), "place3d_16ch", np.zeros(6), base, n_resamples=5)


def test_subset_records_are_cached_and_sum_to_the_psog():
    from place3d_kernels.pooled import PooledPSOG

    spec = _spec()
    first = spec_subset_records(spec)
    again = spec_subset_records(spec)                     # from the on-disk cache
    assert [r.label for r in first] == [r.label for r in again]
    for a, b in zip(first, again):
        assert np.array_equal(a.voxels, b.voxels) and np.array_equal(a.counts, b.counts)
    whole, pooled = spec.build(), PooledPSOG(spec.grid.grid(), first).psog()
    assert np.array_equal(whole.voxels, pooled.voxels) and np.array_equal(whole.probs, pooled.probs)


# ------------------------------------------------------------------ (e) study
def test_study_has_interval_columns_and_within_noise(tmp_path, capsys):
    cfg = tmp_path / "s.toml"
    cfg.write_text('[study]\nname = "t"\nplacements = ["center", "line", "pyramid"]\nvoxel_size = 0.8\n'
                   '[[scenes]]\nname = "town"\nseed = 0\nframes = 16\n[[conditions]]\nname = "clean"\n')
    out = tmp_path / "st"
    assert main(["study", str(cfg), "--output", str(out), "--quiet", "--resamples", "20"]) == 0
    rows = list(csv.DictReader((out / "study.csv").open()))
    assert len(rows) == 3
    for r in rows:
        for t in ("seg", "det"):
            lo, hi = float(r[f"ci_lo_{t}"]), float(r[f"ci_hi_{t}"])
            assert lo <= hi and np.isfinite(lo)
    js = json.loads((out / "study.json").read_text())
    assert js["settings"]["resamples"] == 20 and "town-s0/clean" in js["within_noise"]
    assert all("samples_seg" not in r for r in js["rows"])
    # other resamples change the outputs: a rerun in the same folder is refused, unless --overwrite
    capsys.readouterr()
    assert main(["study", str(cfg), "--output", str(out), "--quiet", "--resamples", "0"]) == 2
    assert "resamples" in capsys.readouterr().err
    assert main(["study", str(cfg), "--output", str(out), "--quiet", "--resamples", "0", "--overwrite"]) == 0
    rows0 = list(csv.DictReader((out / "study.csv").open()))
    assert [(r["msog_seg"], r["msog_det"]) for r in rows0] == [(r["msog_seg"], r["msog_det"]) for r in rows]
    assert all(r["ci_lo_seg"] == "" for r in rows0)


def test_jackknife_se_of_a_mean_is_the_textbook_standard_error():
    # for a mean the delete-one jackknife se equals s / sqrt(n) exactly, and its bias estimate is 0
    from place3d_kernels.uncertainty import Jackknife

    rng = np.random.default_rng(5)
    x = rng.normal(size=(12, 3)) * np.array([1.0, 2.0, 0.5]) + np.array([0.0, 0.3, 3.0])
    n = len(x)
    loo = (x.sum(axis=0) - x) / (n - 1)
    jk = Jackknife(["a", "b", "c"], x.mean(axis=0), loo, level=0.95, unit="subsets", n_units=n)
    np.testing.assert_allclose(jk.se, x.std(axis=0, ddof=1) / np.sqrt(n), rtol=1e-12)
    np.testing.assert_allclose(jk.bias, 0.0, atol=1e-12)
    lo, hi = jk.ci.T
    assert np.all(lo < jk.point) and np.all(jk.point < hi)
    # pairwise: Phi of the difference over the se of the difference, which for means is the paired-t se
    d = x[:, 2] - x[:, 0]
    from scipy.stats import norm

    assert jk.order_freq[2, 0] == pytest.approx(norm.cdf(d.mean() / (d.std(ddof=1) / np.sqrt(n))), rel=1e-9)
    assert jk.order_freq[2, 0] + jk.order_freq[0, 2] == pytest.approx(1.0)


def test_evaluate_default_jackknife_matches_the_records(tmp_path):
    from place3d_kernels.uncertainty import jackknife_records

    out = tmp_path / "eval.json"
    assert main(["evaluate", *TINY, *NAMES, "--output", str(out)]) == 0
    d = json.loads(out.read_text())
    rows, bs = d["rows"], d["bootstrap"]
    assert bs["interval"] == "jackknife" and bs["n_units"] == 4
    order = [r["placement"] for r in rows]
    jk = jackknife_records(spec_subset_records(_spec()), _spec().grid.grid(), "place3d_16ch",
                           {n: Placement.load(n) for n in order}, ("seg", "det"), "sog",
                           point={t: [r[f"msog_{t}"] for r in rows] for t in ("seg", "det")})
    for task in ("seg", "det"):
        for i, r in enumerate(rows):
            assert r["ci"][task] == jk[task].ci[i].tolist()
            assert r["ci"][task][0] <= r[f"msog_{task}"] <= r["ci"][task][1]   # contains the printed score


@pytest.mark.parametrize("ahead, normalisation", [("0", "paper"), ("1", "paper"), ("1", "uncertain")])
def test_optimize_reports_intervals_of_the_best_rig_and_the_baselines(tmp_path, monkeypatch, ahead, normalisation):
    # ahead "1": the left-out grids are prepared on a thread during the search (place3d_app.prefetch.prepare_in_background)
    # where the jackknife takes them (the paper's normalisation); uncertain, optimize's default, takes the
    # unprepared path and must give the library's intervals all the same
    from place3d_app.prefetch import PREFETCH_ENV
    from place3d_kernels.uncertainty import rig_vs_baselines_intervals

    monkeypatch.setenv(PREFETCH_ENV, ahead)
    out = tmp_path / "opt"
    assert main(["optimize", *TINY, "--max-evals", "24", "--normalisation", normalisation, "--output", str(out)]) == 0
    d = json.loads((out / "result.json").read_text())
    iv = d["intervals"]
    assert iv["method"] == "jackknife" and iv["unit"] == "subsets" and iv["n_units"] == 4
    assert iv["best"]["score"] == pytest.approx(d["best_score"], abs=1e-12)
    assert {r["name"] for r in iv["baselines"]} == set(d["baseline_scores"])
    # the same numbers from the library call
    want = rig_vs_baselines_intervals(_spec(), "place3d_16ch", np.asarray(d["best_placement"]),
                                      {n: Placement.load(n) for n in d["baseline_scores"]}, "seg", "sog",
                                      method="jackknife", best_name="optimised", normalisation=normalisation)
    assert d["normalisation"] == normalisation
    assert iv["best"]["ci"] == want["best"]["ci"]
    for r, w in zip(sorted(iv["baselines"], key=lambda r: r["name"]),
                    sorted(want["baselines"], key=lambda r: r["name"])):
        assert r == w
    assert main(["optimize", *TINY, "--max-evals", "24", "--interval", "none", "--output", str(tmp_path / "n")]) == 0
    assert json.loads((tmp_path / "n" / "result.json").read_text())["intervals"] is None
