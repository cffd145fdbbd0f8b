"""Pools kept between commands (``pool_memo.keep_pools``, what ``place3d serve`` turns on): a pool of the same
cache files comes back with its P-SOG and grids; a rewritten file, a record from a worker or a process that keeps
nothing pools again; a kept pool is shared and refuses records; a served command's answer does not change."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from place3d_app.cli import build_parser, main
from place3d_app.commands.routes import drive_specs
from place3d_kernels import pool_memo
from place3d_kernels.pooled import DriveRecord, pool_specs
from place3d_kernels.spec import specs_from_args

TINY = ["--frames", "8", "--voxel-size", "0.8", "--quiet"]


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "cache"))
    pool_memo.keep_pools(2)
    yield
    pool_memo.keep_pools(0)


def _specs(argv):
    args = build_parser().parse_args(argv)
    return args, drive_specs(args, specs_from_args(args))


def _same(a, b):
    return (a.n_subsets == b.n_subsets and np.array_equal(a.voxels, b.voxels)
            and np.array_equal(a.counts, b.counts) and np.array_equal(a.probs, b.probs))


def test_a_pool_of_the_same_files_is_kept_with_its_psog(capsys):
    _, specs = _specs(["evaluate", *TINY, "--route-seeds", "1-2", "--backend", "warp:cpu"])
    built = pool_specs(specs, backend="warp:cpu")            # built here (no files before): not kept
    assert not built.shared
    first = pool_specs(specs, backend="warp:cpu")            # every drive read from its file: kept
    assert first is not built and first.shared
    psog = first.kept_psog()
    assert first.kept_psog() is psog and _same(psog, built.psog())
    capsys.readouterr()
    again = pool_specs(specs, backend="warp:cpu", progress=True)
    assert again is first and again.kept_psog() is psog
    lines = capsys.readouterr().err.splitlines()
    assert lines == [f"  drive {i}/2 {s.scene.label}: pooled by an earlier command" for i, s in enumerate(specs, 1)]
    with pytest.raises(ValueError, match="shared"):
        first.add(first.records[0])
    # another set of drives, or the same ones in another order, is another pool
    assert pool_specs(specs[::-1], backend="warp:cpu") is not first


def test_a_rewritten_file_or_a_workers_record_pools_again():
    _, specs = _specs(["evaluate", *TINY, "--route-seeds", "3-4", "--backend", "warp:cpu"])
    pool_specs(specs, backend="warp:cpu")
    first = pool_specs(specs, backend="warp:cpu")
    assert first.shared
    f = specs[0].cache_file()
    tmp = f.with_name(f.name + ".tmp")
    tmp.write_bytes(f.read_bytes())
    os.replace(tmp, f)                                          # the cache's own way of writing: a new inode
    second = pool_specs(specs, backend="warp:cpu")
    assert second is not first and second.shared and _same(second.psog(), first.psog())
    assert pool_specs(specs, backend="warp:cpu") is second
    # read (as routes.pooled_psog reads, before the pool is made), then a file rewritten before the pooling: the
    # identities taken before the reads no longer hold, so the pool is not kept
    from place3d_kernels.pooled import cached_records

    pool_memo.keep_pools(0)
    pool_memo.keep_pools(2)
    key = pool_memo.pool_files_key(specs)
    read = cached_records(specs)
    tmp.write_bytes(f.read_bytes())
    os.replace(tmp, f)
    late = pool_specs(specs, backend="warp:cpu", read=read, files_key=key)
    assert not late.shared and pool_memo.kept_pool(pool_memo.pool_files_key(specs)) is None
    key = pool_memo.pool_files_key(specs)
    assert pool_specs(specs, backend="warp:cpu", read=cached_records(specs), files_key=key).shared
    # a record made elsewhere (a worker's) is not the file's content by identity: that pool is not kept
    rec = DriveRecord.from_psog(specs[0].build(backend="warp:cpu"), specs[0].scene.label)
    mixed = pool_specs(specs, backend="warp:cpu", known={specs[0]: rec})
    assert mixed is not second and not mixed.shared
    # keep nothing: every call pools again, and what was kept is forgotten
    pool_memo.keep_pools(0)
    assert pool_specs(specs, backend="warp:cpu") is not second
    assert pool_memo.kept_pool(pool_memo.pool_files_key(specs)) is None
    with pytest.raises(ValueError, match="n >= 0"):
        pool_memo.keep_pools(-1)


def test_at_most_n_pools_are_kept_most_recent_last():
    _, specs = _specs(["evaluate", *TINY, "--route-seeds", "5-7", "--backend", "warp:cpu"])
    pools = [specs[0:2], specs[1:3], specs[0:3:2]]
    for p in pools:
        pool_specs(p, backend="warp:cpu")
    kept = [pool_specs(p, backend="warp:cpu") for p in pools]      # the third pushes the first out
    assert [pool_memo.kept_pool(pool_memo.pool_files_key(p)) is k for p, k in zip(pools, kept)] == [False, True, True]


def test_served_commands_on_a_kept_pool_answer_as_a_fresh_process(tmp_path, monkeypatch):
    # optimize again and again in one process that keeps pools (from the third on it takes the kept searched and
    # held-out pools with their grids: the first builds the drives, the second reads them) and once keeping
    # nothing: the same result, bit for bit
    argv = ["optimize", *TINY, "--route-seeds", "3-4", "--holdout-seeds", "10-11", "--max-evals", "24",
            "--backend", "warp:cpu", "--seed", "1"]
    monkeypatch.setenv("PLACE3D_JACKKNIFE_PREFETCH", "1")          # the held-out pool made on its thread
    hits, real = [], pool_memo.kept_pool

    def spy(key):
        got = real(key)
        hits.append(got is not None)
        return got

    monkeypatch.setattr(pool_memo, "kept_pool", spy)
    monkeypatch.setattr("place3d_kernels.pooled.kept_pool", spy)
    keys = ("best_score", "best_placement", "baseline_scores", "intervals", "holdout", "diagnostics", "transfer")
    outs, used = [], []
    for i, keep in enumerate((2, 2, 2, 0)):
        pool_memo.keep_pools(keep)
        hits.clear()
        assert main([*argv, "--output", str(tmp_path / f"o{i}")]) == 0
        used.append(sum(hits))
        r = json.loads((tmp_path / f"o{i}" / "result.json").read_text())
        outs.append({k: r[k] for k in keys})
    assert used[0] == 0 and used[2] >= 2 and used[3] == 0       # searched and held-out pools both kept
    assert outs[0] == outs[1] == outs[2] == outs[3]
