"""``place3d optimize`` errors name the command's options, before any work (issue 33, item 6, "Noise").

Before, these values were refused by the library after the P-SOG was built, in the library's words:
"popsize must be an int >= 2", "seed must be an int >= 0", "restarts cannot be combined with checkpoint",
"MinDistance needs a positive finite distance", "... or use resume=False".
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from place3d_app.cli import main

TINY = ["optimize", "--frames", "8", "--voxel-size", "0.8", "--quiet", "--backend", "warp:cpu", "--routes", "1",
        "--max-evals", "10", "--interval", "none"]


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PLACE3D_CACHE", str(tmp_path / "cache"))


@pytest.mark.parametrize("extra, option", [
    (["--popsize", "1"], "--popsize"),
    (["--sigma0", "0"], "--sigma0"),
    (["--delta", "0"], "--delta"),
    (["--opt-seed", "-1"], "--opt-seed"),
    (["--seed", "4294967296"], "--opt-seed (default: --seed)"),
    (["--restarts", "-1"], "--restarts"),
    (["--restarts", "1", "--checkpoint", "c.ckpt"], "--checkpoint"),
    (["--min-distance", "0"], "--min-distance"),
    (["--min-distance", "5"], "--min-distance 5 cannot hold"),
    (["--fixed-height", "nan"], "--fixed-height"),
])
def test_bad_search_options_are_named_before_any_work(tmp_path, capsys, extra, option):
    assert main(TINY + extra) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("place3d: error: "), err
    assert option in err[0]
    # the library's own words, not preceded by "--"
    assert not re.search(r"(?<![-\w])(popsize|sigma0|seed|restarts|delta) (must|cannot)|MinDistance|resume=", err[0])
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").rglob("psog-*.npz"))


def test_a_checkpoint_of_another_setup_names_the_option_and_the_parameter(tmp_path):
    from place3d_kernels.optimize import SearchSpace, optimize

    space = SearchSpace(n_lidars=1)

    def f(X):
        return -np.sum(np.atleast_2d(X) ** 2, axis=1)

    ck = tmp_path / "c.ckpt"
    optimize(f, space, [], max_evals=12, seed=0, checkpoint=ck, progress=False)
    with pytest.raises(ValueError) as e:
        optimize(f, space, [], max_evals=12, seed=1, checkpoint=ck, resume=True, progress=False)
    assert "--resume" in str(e.value) and "resume=False" in str(e.value)
