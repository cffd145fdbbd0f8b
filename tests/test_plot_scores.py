"""The intervals' figure names the method that made them (issue 33, item 6: ``eval.png`` called jackknife
intervals "bootstrap").

Before, ``plot_scores``'s default title was "M-SOG with bootstrap intervals" whatever it drew, and the
legend of a jackknife over routes said "drives".
"""

from __future__ import annotations

import numpy as np
import pytest

from place3d_kernels import atomic
from place3d_kernels.uncertainty import Bootstrap, Jackknife, plot_scores


@pytest.fixture
def texts(monkeypatch):
    """The figure's title and legend texts, instead of a file."""
    seen = []

    def capture(fig, path, **kw):
        seen.append(fig._suptitle.get_text())
        for ax in fig.axes:
            if ax.get_legend() is not None:
                seen.extend(t.get_text() for t in ax.get_legend().get_texts())
        return path

    monkeypatch.setattr(atomic, "atomic_savefig", capture)
    return seen


def _samples(n, rng):
    return rng.normal(-0.03, 0.002, size=(n, 3))


@pytest.mark.parametrize("make, words, wrong", [
    (lambda r: Jackknife(["a", "b", "c"], np.array([-0.03, -0.031, -0.032]), _samples(5, r), unit="subsets",
                         n_units=5),
     ["jackknife over 5 subsets"], ["bootstrap", "routes"]),
    (lambda r: Jackknife(["a", "b", "c"], np.array([-0.03, -0.031, -0.032]), _samples(8, r), unit="drives",
                         n_units=8, strata=("A",) * 4 + ("B",) * 4, df=6),
     ["jackknife over 8 routes", "stratified by scene", "t with 6 df"], ["bootstrap", "drives"]),
    (lambda r: Bootstrap(["a", "b", "c"], np.array([-0.03, -0.031, -0.032]), _samples(40, r), unit="subsets",
                         n_units=6),
     ["bootstrap over 6 subsets", "40 resamples"], ["jackknife"]),
])
def test_title_and_legend_name_the_method(tmp_path, texts, make, words, wrong):
    b = make(np.random.default_rng(0))
    plot_scores({"seg": b, "det": b}, tmp_path / "p.png")
    title, legend = texts[0], " ".join(texts[1:])
    for w in words:
        assert w in title and w in legend, (w, title, legend)
    for w in wrong:
        assert w not in title and w not in legend, (w, title, legend)
