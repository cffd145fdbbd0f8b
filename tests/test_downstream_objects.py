"""place3d downstream (issue 35), the second part on tiny data: instance ids from the ray cast in the .label
files, the detection proxy (object recall) against hand-computed cases, dataset tasks on Ray giving the
local files, and resume of sequences and cells made before the proxy."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from place3d_kernels.classes import CLASS_ID, VEHICLE  # noqa: E402
from place3d_kernels.downstream import metrics as dm  # noqa: E402
from place3d_kernels.downstream.dataset import (Splits, build_datasets, instance_tables, pack_labels,  # noqa: E402
                                                read_frames, sequence_folder, sequence_spec,
                                                unpack_labels, write_drive)

from downstream_common import BACKEND, _one_thread, _rig, needs_backend, tiny_lidar_file  # noqa: E402,F401

PEDESTRIAN = CLASS_ID["pedestrian"]


@pytest.fixture
def tiny_lidar(tmp_path):
    return tiny_lidar_file(tmp_path, 8, (-25.0, 2.0), 256)


# ------------------------------------------------------------------------------------ instance ids
def test_label_packing_is_the_semantickitti_layout():
    raw = pack_labels([10, 4, 7, 0], [3, 65535, 0, 0])
    assert raw.dtype == np.uint32
    # the class in the low 16 bits, the instance in the high 16 (semantic-kitti-api: label & 0xFFFF, label >> 16)
    np.testing.assert_array_equal(raw, [3 * 65536 + 10, 65535 * 65536 + 4, 7, 0])
    cls, inst = unpack_labels(raw)
    np.testing.assert_array_equal(cls, [10, 4, 7, 0])
    np.testing.assert_array_equal(inst, [3, 65535, 0, 0])
    with pytest.raises(ValueError, match="16 bits"):
        pack_labels([1], [65536])


@needs_backend
def test_simulate_hit_faces_names_the_triangle_of_each_return(tiny_lidar):
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.pooled import Drive
    from place3d_kernels.simulate import simulate

    scene = Drive("town", 3, 2).build()
    lidar = LidarModel.load(tiny_lidar)
    plain = simulate(scene, lidar, backend=BACKEND)
    frames, faces = simulate(scene, lidar, backend=BACKEND, hit_faces=True)
    for f, (a, b, (on_actor, face)) in enumerate(zip(plain, frames, faces)):
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.labels, b.labels)
        np.testing.assert_array_equal(a.intensity, b.intensity)
        # the face's label is the return's label, in the mesh it came from
        dyn = scene.dynamic(f)
        lab = np.where(on_actor, dyn.labels[np.where(on_actor, face, 0)], scene.static.labels[np.where(on_actor, 0, face)])
        np.testing.assert_array_equal(lab, b.labels)
        assert on_actor.any() and not on_actor.all()


@needs_backend
def test_instance_ids_round_trip_and_name_the_actor_hit(tmp_path, tiny_lidar):
    from place3d_kernels.io import read_semantickitti
    from place3d_kernels.io.semantickitti import frame_paths
    from place3d_kernels.pose import invert, pose_matrix, transform_points

    rig = _rig(tiny_lidar)
    splits = Splits(("town",), (3,), (4,), 2)
    build_datasets(tmp_path, [rig], splits, backend=BACKEND)
    d = splits.drives("train")[0]
    scene = d.build()
    (frames,) = read_frames(tmp_path, rig, [d], instances=True)
    static, _ = instance_tables(scene)
    moving, parked = set(), set()
    for f, (pts, lab, inst) in enumerate(frames):
        # the classes read by the package's reader (low 16 bits) are the classes written
        _, _, place3d = read_semantickitti(*frame_paths(sequence_folder(tmp_path, rig, d), f), labels="place3d")
        np.testing.assert_array_equal(place3d, lab)
        is_object = np.isin(lab, [VEHICLE, PEDESTRIAN])
        assert np.all(inst[is_object] > 0) and np.all(inst[~is_object] == 0)
        # instance k <= len(actors) lies on actor k - 1: inside its posed mesh bounds; a larger k is a parked
        # car: inside the bounds of the static triangles of that id
        world = transform_points(pose_matrix(scene.ego_poses[f]), pts.astype(np.float64))
        for k in np.unique(inst[inst > 0]):
            if k <= len(scene.actors):
                actor = scene.actors[k - 1]
                local = transform_points(invert(pose_matrix(actor.poses[f])), world[inst == k])
                lo, hi = actor.mesh.bounds
                assert set(lab[inst == k].tolist()) == {int(actor.mesh.labels[0])}
                moving.add(int(k))
            else:
                local = world[inst == k]
                corners = scene.static.vertices[scene.static.faces[static == k]].reshape(-1, 3)
                lo, hi = corners.min(axis=0), corners.max(axis=0)
                assert set(lab[inst == k].tolist()) == {VEHICLE}
                parked.add(int(k))
            assert np.all(local >= lo - 0.01) and np.all(local <= hi + 0.01), k
    assert len(moving) >= 2 and len(parked) >= 2


def test_parked_cars_get_their_own_ids():
    from place3d_kernels.downstream.dataset import _touching_parts
    from place3d_kernels.pooled import Drive

    scene = Drive("opendrive:Town01", 0, 1).build()
    static, actors = instance_tables(scene)
    boxes = scene.meta["static_boxes"]
    n_act = len(scene.actors)
    cars = scene.static.labels == VEHICLE
    assert len(boxes) > 0 and len(actors) == sum(a.mesh.n_faces for a in scene.actors)
    # every parked car's triangles, and only vehicle triangles, carry an id after the actors' ids
    assert np.all(static[cars] > n_act) and np.all(static[~cars] == 0)
    np.testing.assert_array_equal(np.unique(static[cars]), n_act + 1 + np.arange(len(boxes)))
    np.testing.assert_array_equal(np.unique(actors), np.arange(1, n_act + 1))
    # the grouping used where no boxes are recorded finds the same cars as the boxes here
    groups = _touching_parts(scene.static, np.flatnonzero(cars))
    assert len(set(zip(groups.tolist(), static[cars].tolist()))) == len(boxes) == groups.max() + 1
    # the embedded town records no boxes: each group it finds has the footprint of one car or van
    town = Drive("town", 0, 1).build()
    static, _ = instance_tables(town)
    ids = np.unique(static[static > 0])
    assert len(ids) > 10 and ids[0] == len(town.actors) + 1
    for k in ids:
        corners = town.static.vertices[town.static.faces[static == k]].reshape(-1, 3)
        short, long = np.sort(corners.max(axis=0)[:2] - corners.min(axis=0)[:2])
        assert 1.7 < short < 2.1 and 3.9 < long < 5.7, (k, short, long)


# ------------------------------------------------------------------------------------ proxy metric
def test_instance_rows_count_points_and_hits_per_object():
    from place3d_kernels.downstream.train import _instance_rows

    inst = torch.tensor([0, 1, 1, 1, 2, 2, 1, 3])
    lab = torch.tensor([7, 10, 10, 10, 4, 4, 10, 9])
    pred = torch.tensor([7, 10, 7, 10, 4, 9, 10, 9])
    frame = torch.tensor([0, 0, 0, 0, 0, 0, 1, 1])
    rows = _instance_rows(inst, lab, pred, frame, (10, 4))
    # (frame, instance, class, points, hits); instance 3 is of a class not counted, instance 0 is none
    np.testing.assert_array_equal(rows, [[0, 1, 10, 3, 2], [0, 2, 4, 2, 1], [1, 1, 10, 1, 1]])


def test_detection_counts_and_recall_against_hand_computed_values():
    def t(*rows):
        return np.array(rows, np.int64).reshape(-1, 6)

    # two rigs, two seeds, two drives; rows: drive, frame, instance, class, points, points predicted right
    a0 = t([0, 0, 1, 10, 10, 10], [0, 0, 2, 10, 6, 2], [1, 3, 1, 10, 20, 15], [1, 3, 5, 4, 8, 8])
    a1 = t([0, 0, 1, 10, 10, 4], [0, 0, 2, 10, 6, 6], [1, 3, 1, 10, 20, 9], [1, 3, 5, 4, 8, 0])
    b0 = t([0, 0, 1, 10, 3, 3], [0, 0, 2, 10, 9, 9], [0, 1, 7, 10, 12, 12])
    b1 = t([0, 0, 1, 10, 3, 3], [0, 0, 2, 10, 9, 5], [0, 1, 7, 10, 12, 5])
    c = dm.detection_counts([[a0, a1], [b0, b1]], 2, VEHICLE)
    # vehicles seen with >= 5 points by some rig: drive 0: (0,1) by a, (0,2) by both, (1,7) by b; drive 1: (3,1)
    np.testing.assert_array_equal(c["objects"], [3, 1])
    np.testing.assert_array_equal(c["seen"], [[2, 1], [2, 0]])
    # found: >= 5 right and >= half right. a0: (0,1) yes, (0,2) 2 < 5 no, (3,1) yes -> [1, 1]
    # a1: (0,1) 4 < 5 no, (0,2) yes, (3,1) 9 < 10 (half of 20) no -> [1, 0]
    # b0: (0,1) 3 points no, (0,2) yes, (1,7) yes, (3,1) unseen -> [2, 0]; b1: (0,2) 5 >= 4.5 yes, (1,7) 5 < 6 no
    np.testing.assert_array_equal(c["found"], [[[1, 1], [1, 0]], [[2, 0], [1, 0]]])
    boot = dm.bootstrap_recall(c["found"], c["objects"], resamples=200)
    np.testing.assert_allclose(boot["per_seed"], [[2 / 4, 1 / 4], [2 / 4, 1 / 4]])
    np.testing.assert_allclose(boot["recall"], [3 / 8, 3 / 8])
    assert np.all(boot["lo"] <= boot["recall"]) and np.all(boot["recall"] <= boot["hi"])
    ped = dm.detection_counts([[a0, a1], [b0, b1]], 2, PEDESTRIAN)
    np.testing.assert_array_equal(ped["objects"], [0, 1])
    np.testing.assert_array_equal(ped["found"], [[[0, 1], [0, 0]], [[0, 0], [0, 0]]])


def test_recall_tau_follows_the_order_of_the_rigs():
    found = np.array([[[1, 2], [1, 1]], [[2, 2], [2, 3]], [[3, 3], [3, 4]]])
    objects = np.array([4, 4])
    up = dm.bootstrap_recall_tau([1.0, 2.0, 3.0], found, objects, resamples=100)
    assert up["tau"] == pytest.approx(1.0) and up["p_positive"] == 1.0
    assert dm.bootstrap_recall_tau([3.0, 2.0, 1.0], found, objects, resamples=20)["tau"] == pytest.approx(-1.0)
    # identical drives: the interval is that of the seeds alone
    same = dm.bootstrap_recall(np.array([[[1, 1], [3, 3]]]), np.array([4, 4]), resamples=200)
    assert same["lo"][0] == pytest.approx(0.25) and same["hi"][0] == pytest.approx(0.75)


# ------------------------------------------------------------------------------------ Ray and resume
@needs_backend
def test_ray_tasks_write_the_files_of_the_local_path_and_resume(tmp_path, tiny_lidar):
    pytest.importorskip("ray")
    from place3d_app.executors import RayExecutor
    from place3d_kernels.manifest import read_manifest
    from place3d_kernels.pooled import PoolSettings

    rig = _rig(tiny_lidar)
    splits = Splits(("town",), (0,), (4,), 2)
    settings = PoolSettings(0.2, frames_per_subset=1, backend=BACKEND, cache=str(tmp_path / "cache"))
    _, here = build_datasets(tmp_path / "a", [rig], splits, BACKEND, psog=settings)
    with RayExecutor(num_cpus=1) as ex:
        tot, there = build_datasets(tmp_path / "b", [rig], splits, BACKEND, psog=settings, executor=ex)
        assert tot["written"] == 2 and ex.submitted == 2
        again, _ = build_datasets(tmp_path / "b", [rig], splits, BACKEND, psog=settings, executor=ex)
    assert again["written"] == 0 and again["skipped"] == 2
    np.testing.assert_array_equal(here[0].counts, there[0].counts)
    for d in splits.all_drives():
        a, b = sequence_folder(tmp_path / "a", rig, d), sequence_folder(tmp_path / "b", rig, d)
        names = sorted(str(p.relative_to(a)) for p in a.rglob("*") if p.is_file())
        assert names == sorted(str(p.relative_to(b)) for p in b.rglob("*") if p.is_file())
        for n in names:
            if n == "sequence.json":           # its provenance (time, command line) differs; its spec may not
                assert read_manifest(a / n)["spec"] == read_manifest(b / n)["spec"]
            else:
                assert (a / n).read_bytes() == (b / n).read_bytes(), n


@needs_backend
def test_sequences_written_before_instance_ids_are_written_again(tmp_path, tiny_lidar):
    from place3d_kernels.io.semantickitti import SEQUENCE_META
    from place3d_kernels.manifest import write_manifest

    rig = _rig(tiny_lidar)
    d = Splits(("town",), (3,), (4,), 2).drives("train")[0]
    write_drive(tmp_path, [rig], d, BACKEND)
    folder = sequence_folder(tmp_path, rig, d)
    want = [(folder / "labels" / f"{i:06d}.label").read_bytes() for i in range(2)]
    # as a study before the detection proxy left it: classes only, a manifest without "instances"
    for i in range(2):
        p = folder / "labels" / f"{i:06d}.label"
        p.write_bytes((np.fromfile(p, np.uint32) & 0xFFFF).astype(np.uint32).tobytes())
    old = {k: v for k, v in sequence_spec(rig, d).items() if k != "instances"}
    write_manifest(folder / SEQUENCE_META, old)
    assert write_drive(tmp_path, [rig], d, BACKEND)["written"] == [rig.name]
    assert [(folder / "labels" / f"{i:06d}.label").read_bytes() for i in range(2)] == want
    assert write_drive(tmp_path, [rig], d, BACKEND)["skipped"] == [rig.name]
    # other settings are still refused, not rewritten
    write_manifest(folder / SEQUENCE_META, {**old, "merged": "something else"})
    with pytest.raises(ValueError, match="different settings"):
        write_drive(tmp_path, [rig], d, BACKEND)


def _study_args(out, lidar, *extra):
    from place3d_app.commands import downstream as command

    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="command")
    command.add_parser(sub)
    return ap.parse_args(["downstream", "--rigs", "center,pyramid", "--lidar", lidar, "--towns", "town",
                          "--heldout-towns", "", "--train-routes", "0", "--test-routes", "9", "--frames", "2",
                          "--steps", "2", "--seeds", "0", "--bev-cells", "16", "--width", "4", "--depth", "2",
                          "--resamples", "20", "--device", "cpu", "--backend", BACKEND or "reference",
                          "--output", str(out), "--quiet", *extra])


@needs_backend
def test_study_reports_the_proxy_and_retrains_cells_made_before_it(tmp_path, tiny_lidar, capsys):
    from place3d_app.commands import downstream as command

    args = _study_args(tmp_path / "study", tiny_lidar)
    assert command.run(args) == 0
    res = json.loads((tmp_path / "study" / "results.json").read_text())
    objects = res["table"]["bev"]["test"]["objects"]
    assert set(objects) == {"vehicle", "pedestrian"}
    veh = objects["vehicle"]
    assert veh["objects"] > 0 and veh["thresholds"]["detect_min_share"] == dm.DETECT_MIN_SHARE
    assert [r["rig"] for r in veh["rows"]] == ["center", "pyramid"]
    assert all(0.0 <= r["lo"] <= r["recall"] <= r["hi"] <= 1.0 and 0.0 < r["seen"] <= 1.0 for r in veh["rows"])
    assert set(veh["tau"]) == {"paper", "evidence", "uncertain"}
    header = (tmp_path / "study" / "table.csv").read_text().splitlines()[0]
    assert "vehicle_recall" in header and "pedestrian_seen" in header
    assert "vehicle recall (detection proxy" in capsys.readouterr().out
    # a cell written before the proxy (no object tables) is trained again; the other one resumes
    cell = next((tmp_path / "study" / "cells" / "center").glob("bev-s0-*.npz"))
    with np.load(cell) as z:
        kept = {k: z[k] for k in z.files if not k.startswith("objects_")}
    np.savez_compressed(cell, **kept)
    assert command.run(args) == 0
    again = json.loads((tmp_path / "study" / "results.json").read_text())
    assert again["cells_run"] == 1 and again["cells_skipped"] == 1
    assert again["table"]["bev"]["test"]["objects"]["vehicle"]["rows"] == veh["rows"]


def test_executor_options_follow_the_other_commands(tmp_path, capsys):
    from place3d_app.commands import downstream as command

    args = _study_args(tmp_path / "s", "place3d_16ch", "--executor", "ray", "--workers", "2")
    assert command.run(args) == 2
    assert "--num-cpus" in capsys.readouterr().err
    workers, ex = command.dataset_executor(_study_args(tmp_path / "s", "place3d_16ch", "--workers", "3"), 4)
    assert workers == 3 and ex is None
    workers, ex = command.dataset_executor(_study_args(tmp_path / "s", "place3d_16ch", "--executor", "local"), 4)
    assert workers == 0 and ex is None
