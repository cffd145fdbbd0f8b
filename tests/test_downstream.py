"""place3d downstream (issue 35) on tiny data: the dataset writer, one training step, the mIoU code against
hand-computed confusion matrices, and resume."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import place3d_kernels as p3k  # noqa: E402
from place3d_kernels.downstream import metrics as dm  # noqa: E402
from place3d_kernels.downstream.dataset import (Rig, Splits, build_datasets, read_frames, sequence_folder,  # noqa: E402
                                                simulate_rig, write_drive)

from downstream_common import BACKEND, _one_thread, _rig, needs_backend, tiny_lidar_file  # noqa: E402,F401
TINY_MODEL = {"bev_cells": 16, "range_shape": (8, 32), "width": 4, "depth": 2, "point_width": 8}


@pytest.fixture
def tiny_lidar(tmp_path):
    return tiny_lidar_file(tmp_path, 4, (-20.0, 0.0), 64)


# ------------------------------------------------------------------------------------------ dataset
def test_splits_refuse_shared_routes_and_trained_heldout_towns():
    with pytest.raises(ValueError, match="disjoint"):
        Splits(("town",), (0, 1), (1, 2), 4)
    with pytest.raises(ValueError, match="held-out"):
        Splits(("Town01",), (0,), (1,), 4, heldout_towns=("Town01",))
    s = Splits(("town",), (0, 1), (5,), 3, heldout_towns=("Town01",))
    assert [d.seed for d in s.drives("train")] == [0, 1]
    assert [(d.scene, d.seed) for d in s.drives("heldout")] == [("opendrive:Town01", 5)]
    train = {(d.scene, d.seed) for d in s.drives("train")}
    assert not train & {(d.scene, d.seed) for d in s.drives("test") + s.drives("heldout")}


@needs_backend
def test_dataset_writer_semantickitti_layout_ego_frame_and_resume(tmp_path, tiny_lidar):
    from place3d_kernels.io import read_sequence
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.pose import invert, pose_matrix, transform_points
    from place3d_kernels.simulate import simulate

    rig = _rig(tiny_lidar)
    splits = Splits(("town",), (0,), (7,), 2)
    tot, records = build_datasets(tmp_path, [rig], splits, backend=BACKEND)
    assert records == [] and tot["written"] == 2 and tot["skipped"] == 0
    for d in splits.all_drives():
        folder = sequence_folder(tmp_path, rig, d)
        for sub, ext in (("velodyne", "bin"), ("labels", "label")):
            assert sorted(p.name for p in (folder / sub).iterdir()) == [f"{i:06d}.{ext}" for i in range(2)]
        assert (folder / "poses.txt").is_file() and (folder / "sequence.json").is_file()
    # the merged cloud is every LiDAR's returns, moved into the ego frame of its frame
    d = splits.drives("test")[0]
    scene = d.build()
    lidar = LidarModel.load(tiny_lidar)
    want = []
    for pose in rig.pose_array:
        fr = simulate(scene, lidar, mount=pose, frames=[1], backend=BACKEND)[0]
        want.append(transform_points(invert(pose_matrix(scene.ego_poses[1])), fr.points))
    want = np.concatenate(want)
    (frames,) = read_frames(tmp_path, rig, [d])
    pts, lab = frames[1]
    assert len(pts) == len(want) > 0
    np.testing.assert_allclose(pts, want, atol=1e-4)
    assert lab.min() >= 0 and lab.max() < len(p3k.CLASSES) and (lab > 0).any()
    # the package's reader takes the sequences as they are (mount zeros and Place3D labels from sequence.json)
    world = read_sequence(sequence_folder(tmp_path, rig, d), frames=[1])[0]
    np.testing.assert_allclose(world.points, transform_points(pose_matrix(scene.ego_poses[1]), pts), atol=1e-3)
    np.testing.assert_array_equal(world.labels, lab)
    # resume: a second run writes nothing; a folder made with another rig under the same name is refused
    again, _ = build_datasets(tmp_path, [rig], splits, backend=BACKEND)
    assert again["written"] == 0 and again["skipped"] == 2
    moved = Rig(rig.name, ((0.0, 0.0, 2.2, 0.0, 0.0, 0.0),), tiny_lidar)
    with pytest.raises(ValueError, match="rig"):
        write_drive(tmp_path, [moved], d, backend=BACKEND)
    assert write_drive(tmp_path, [moved], d, backend=BACKEND, overwrite=True)["written"] == [rig.name]


@needs_backend
def test_worker_processes_write_the_same_sequences_and_records(tmp_path, tiny_lidar):
    from place3d_kernels.pooled import PoolSettings

    rig = _rig(tiny_lidar)
    splits = Splits(("town",), (0,), (4,), 1)
    settings = PoolSettings(0.2, frames_per_subset=1, backend=BACKEND, cache=str(tmp_path / "cache"))
    _, here = build_datasets(tmp_path / "a", [rig], splits, BACKEND, psog=settings)
    _, there = build_datasets(tmp_path / "b", [rig], splits, BACKEND, psog=settings, workers=2)
    assert [r.label for r in here] == [r.label for r in there] == [splits.drives("train")[0].label]
    np.testing.assert_array_equal(here[0].counts, there[0].counts)
    for d in splits.all_drives():
        a, b = sequence_folder(tmp_path / "a", rig, d), sequence_folder(tmp_path / "b", rig, d)
        for sub in ("velodyne/000000.bin", "labels/000000.label", "poses.txt"):
            assert (a / sub).read_bytes() == (b / sub).read_bytes()


@needs_backend
def test_simulate_rig_merges_lidars_in_order(tiny_lidar):
    from place3d_kernels.pooled import Drive

    scene = Drive("town", 3, 1).build()
    one = Rig("one", (_rig(tiny_lidar).poses[0],), tiny_lidar)
    (merged,) = simulate_rig(scene, _rig(tiny_lidar), BACKEND)
    (first,) = simulate_rig(scene, one, BACKEND)
    np.testing.assert_array_equal(merged[0][:len(first[0])], first[0])
    assert len(merged[0]) > len(first[0])


# ------------------------------------------------------------------------------------------ training
def _toy_frames(n=4, pts=1500, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        p = np.stack([rng.uniform(-39, 39, pts), rng.uniform(-39, 39, pts), rng.uniform(-0.5, 5, pts)], 1)
        lab = np.where(p[:, 2] < 0.5, 7, np.where(p[:, 0] > 0, 1, 9))
        out.append((p.astype(np.float32), lab.astype(np.int64)))
    return out


@pytest.mark.parametrize("name", ["bev", "range"])
def test_one_training_step_lowers_the_loss(name):
    from place3d_kernels.downstream.model import ModelConfig, build_model
    from place3d_kernels.downstream.train import FrameBank, class_weights, train_step

    mc = ModelConfig(name=name, **TINY_MODEL)
    bank = FrameBank(_toy_frames(), mc, "cpu")
    torch.manual_seed(0)
    model = build_model(mc)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2)
    p, lab, b = bank.batch([0, 1])
    w = class_weights(bank.labels, mc.n_classes)
    before = train_step(model, opt, p, lab, b, 2, w)
    with torch.no_grad():
        after = float(torch.nn.functional.cross_entropy(model(p, b, 2), lab, weight=w, ignore_index=0))
    assert after < before


def test_class_weights_skip_unlabeled_and_absent_classes():
    from place3d_kernels.downstream.train import class_weights

    w = class_weights(torch.tensor([0, 0, 1, 1, 1, 1, 2]), 4)
    assert w[0] == 0 and w[3] == 0 and w[2] > w[1] > 0
    assert float(w[1:3].mean()) == pytest.approx(1.0)


def test_training_is_repeatable_on_the_cpu():
    from place3d_kernels.downstream.model import ModelConfig
    from place3d_kernels.downstream.train import FrameBank, TrainConfig, train_model

    mc = ModelConfig(name="bev", **TINY_MODEL)
    bank = FrameBank(_toy_frames(), mc, "cpu")
    cfg = TrainConfig(steps=3, batch_size=2)
    a = train_model(bank, mc, cfg, 5, "cpu")[1]["losses"]
    b = train_model(bank, mc, cfg, 5, "cpu")[1]["losses"]
    c = train_model(bank, mc, cfg, 6, "cpu")[1]["losses"]
    assert a == b and a != c


# ------------------------------------------------------------------------------------------ metrics
def test_confusion_and_miou_against_hand_computed_values():
    gt = [1, 1, 2, 2, 2, 0, 3]
    pred = [1, 2, 2, 2, 1, 1, 3]
    conf = dm.confusion_matrix(gt, pred, 4)
    # rows: ground truth, columns: prediction; the unlabeled point (gt 0) is not counted
    np.testing.assert_array_equal(conf, [[0, 0, 0, 0], [0, 1, 1, 0], [0, 1, 2, 0], [0, 0, 0, 1]])
    iou = dm.per_class_iou(conf)
    assert np.isnan(iou[0])
    # class 1: TP 1, FN 1 (-> 2), FP 1 (a 2 taken for 1): 1/3; class 2: TP 2, FN 1, FP 1: 2/4; class 3: 1
    np.testing.assert_allclose(iou[1:], [1 / 3, 1 / 2, 1.0])
    assert dm.miou(conf, [1, 2, 3]) == pytest.approx((1 / 3 + 1 / 2 + 1) / 3)
    assert dm.present_classes(conf) == [1, 2, 3]
    # a class in the list that nobody saw or predicted counts 0, not NaN
    conf5 = np.zeros((5, 5), np.int64)
    conf5[:4, :4] = conf
    assert dm.miou(conf5, [1, 2, 3, 4]) == pytest.approx((1 / 3 + 1 / 2 + 1) / 4)


def test_present_classes_are_those_of_every_rig():
    a = np.diag([0, 5, 3, 0]).astype(np.int64)
    b = np.diag([0, 5, 0, 2]).astype(np.int64)
    assert dm.present_classes(np.stack([a, b])[:, None, None]) == [1]
    assert dm.present_classes(a, min_points=4) == [1]


def test_bootstrap_intervals_and_tau():
    def conf(tp, fp):
        c = np.zeros((3, 3), np.int64)
        c[1, 1], c[2, 2], c[2, 1] = tp, 10, fp
        return c

    # three rigs, two seeds, two drives; rig r is better the larger r
    confs = np.array([[[conf(10 + 5 * r + s, 5) for _ in range(2)] for s in range(2)] for r in range(3)])
    boot = dm.bootstrap_miou(confs, [1, 2], resamples=200)
    per_seed = dm.miou(confs.sum(axis=2), [1, 2])
    np.testing.assert_allclose(boot["miou"], per_seed.mean(axis=1))
    assert np.all(boot["lo"] <= boot["miou"] + 1e-12) and np.all(boot["miou"] <= boot["hi"] + 1e-12)
    # identical drives: the interval comes from the seeds alone, within the two seeds' values
    np.testing.assert_allclose(boot["lo"], per_seed.min(axis=1), atol=1e-12)
    np.testing.assert_allclose(boot["hi"], per_seed.max(axis=1), atol=1e-12)
    tau = dm.bootstrap_tau([1.0, 2.0, 3.0], confs, [1, 2], resamples=100)
    assert tau["tau"] == pytest.approx(1.0) and tau["lo"] == pytest.approx(1.0) and tau["p_positive"] == 1.0
    assert dm.bootstrap_tau([3.0, 2.0, 1.0], confs, [1, 2], resamples=50)["tau"] == pytest.approx(-1.0)


# ------------------------------------------------------------------------------------------ study
def _study_args(out, tiny_lidar, seeds="0"):
    from place3d_app.commands import downstream as command

    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="command")
    command.add_parser(sub)
    return ap.parse_args(["downstream", "--rigs", "center,pyramid", "--lidar", tiny_lidar, "--towns", "town",
                          "--heldout-towns", "", "--train-routes", "0", "--test-routes", "9", "--frames", "2",
                          "--steps", "2", "--seeds", seeds, "--bev-cells", "16", "--width", "4", "--depth", "2",
                          "--resamples", "20", "--device", "cpu", "--backend", BACKEND, "--output", str(out),
                          "--quiet"])


@needs_backend
def test_study_resumes_finished_cells(tmp_path, tiny_lidar, capsys):
    import json

    from place3d_app.commands import downstream as command

    args = _study_args(tmp_path / "study", tiny_lidar)
    assert args.func is command.run
    assert command.run(args) == 0
    res = json.loads((tmp_path / "study" / "results.json").read_text())
    assert res["cells_run"] == 2 and res["cells_skipped"] == 0
    rows = res["table"]["bev"]["test"]["rows"]
    assert [r["rig"] for r in rows] == ["center", "pyramid"]
    assert all(0.0 <= r["lo"] <= r["miou"] <= r["hi"] <= 1.0 for r in rows)
    assert set(rows[0]["msog"]) == {"paper", "evidence", "uncertain"}
    assert (tmp_path / "study" / "msog_vs_miou.png").stat().st_size > 0
    # a second run trains nothing and writes no dataset; a new seed trains only its own cells
    assert command.run(args) == 0
    again = json.loads((tmp_path / "study" / "results.json").read_text())
    assert again["cells_run"] == 0 and again["cells_skipped"] == 2 and again["datasets"]["written"] == 0
    assert again["table"]["bev"]["test"]["rows"] == rows
    assert command.run(_study_args(tmp_path / "study", tiny_lidar, seeds="0,1")) == 0
    more = json.loads((tmp_path / "study" / "results.json").read_text())
    assert more["cells_run"] == 2 and more["cells_skipped"] == 2
    assert "Kendall tau" in capsys.readouterr().out
