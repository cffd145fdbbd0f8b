"""OpenDRIVE scenes: geometry types against closed forms, lane areas, errors, and the CARLA towns."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import fresnel

import place3d_kernels as p3k
from place3d_kernels.classes import CLASS_ID
from place3d_kernels.scene.opendrive import from_opendrive, parse_opendrive

from place3d_kernels.data import opendrive_path  # the four CARLA maps ship with the package
#: README figures (km)
TOWN_LENGTHS = {"Town01": 3.9, "Town03": 9.1, "Town04": 9.75, "Town06": 7.3}


def lanes_xml(left=(("driving", 3.0),), right=(("driving", 3.5),), center_mark="solid", extra=""):
    def lane(i, tp, w, mark="none"):
        return (f'<lane id="{i}" type="{tp}" level="false"><width sOffset="0" a="{w}" b="0" c="0" d="0"/>'
                f'<roadMark sOffset="0" type="{mark}" width="0.15"/></lane>')

    ls = "".join(lane(i + 1, tp, w) for i, (tp, w) in reversed(list(enumerate(left))))
    rs = "".join(lane(-(i + 1), tp, w) for i, (tp, w) in enumerate(right))
    return (f'<lanes>{extra}<laneSection s="0"><left>{ls}</left>'
            f'<center><lane id="0" type="none"><roadMark sOffset="0" type="{center_mark}" width="0.15"/></lane></center>'
            f'<right>{rs}</right></laneSection></lanes>')


def road_xml(rid, length, geometry, lanes=None, junction="-1", elevation=""):
    lanes = lanes if lanes is not None else lanes_xml()
    return (f'<road name="r{rid}" length="{length!r}" id="{rid}" junction="{junction}"><planView>{geometry}</planView>'
            f'<elevationProfile>{elevation}</elevationProfile>{lanes}</road>')


def geom(length, kind, x=0.0, y=0.0, hdg=0.0, s=0.0):
    return f'<geometry s="{s!r}" x="{x!r}" y="{y!r}" hdg="{hdg!r}" length="{length!r}">{kind}</geometry>'


def write(tmp_path, *roads, junctions="", name="t.xodr"):
    p = tmp_path / name
    p.write_text('<?xml version="1.0"?>\n<OpenDRIVE><header revMajor="1" revMinor="4"/>' + "".join(roads)
                 + junctions + "</OpenDRIVE>")
    return p


def label_area(mesh, label):
    v, f = mesh.vertices, mesh.faces[mesh.labels == label]
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return 0.5 * float(np.abs(n[:, 2]).sum())  # horizontal (projected) area


BARE = dict(ground=False, roadside=False, n_traffic=0, n_pedestrians=0, n_lead=0)


def test_straight_road_length_area_and_labels(tmp_path):
    lanes = lanes_xml(left=(("driving", 3.0), ("sidewalk", 2.0)), right=(("driving", 3.5), ("shoulder", 0.5)))
    p = write(tmp_path, road_xml(0, 100.0, geom(100.0, "<line/>"), lanes))
    sc = from_opendrive(p, seed=1, n_frames=5, **BARE)
    assert sc.name == "opendrive-t"
    assert sc.meta["road_length"] == pytest.approx(100.0)
    assert sc.meta["road_area"] == pytest.approx(650.0, rel=1e-6)
    assert sc.meta["area_by_type"]["sidewalk"] == pytest.approx(200.0, rel=1e-6)
    assert label_area(sc.static, 7) == pytest.approx(650.0, rel=1e-6)
    assert label_area(sc.static, 8) == pytest.approx(200.0, rel=1e-6)       # top only; curbs are vertical
    assert label_area(sc.static, 21) == pytest.approx(50.0, rel=1e-6)
    assert label_area(sc.static, 6) == pytest.approx(100.0 * 0.15, rel=1e-6)  # the solid centre line
    v, f, lab = sc.static.vertices, sc.static.faces, sc.static.labels
    zs = v[f[lab == 8]][..., 2]
    assert zs.max() == pytest.approx(0.14)                                      # the raised sidewalk
    assert v[f[lab == 6]][..., 2].min() == pytest.approx(0.02)
    # the ego drives the right lane (y = -1.75) along +x, on the ground
    assert np.allclose(sc.ego_poses[:, 1], -1.75) and np.all(np.diff(sc.ego_poses[:, 0]) > 0)
    assert np.allclose(sc.ego_poses[:, [2, 3, 4, 5]], 0.0)
    assert sc.n_frames == 5 and sc.frame_interval == 0.5


def test_broken_marks_are_dashes(tmp_path):
    p = write(tmp_path, road_xml(0, 90.0, geom(90.0, "<line/>"), lanes_xml(center_mark="broken")))
    sc = from_opendrive(p, n_frames=2, **BARE)
    assert label_area(sc.static, 6) == pytest.approx(30.0 * 0.15, rel=1e-6)  # 3 m on, 6 m off


def test_arc_area_matches_annulus(tmp_path):
    R, theta = 50.0, math.pi / 2
    L = R * theta
    p = write(tmp_path, road_xml(0, L, geom(L, f'<arc curvature="{1 / R!r}"/>')))
    sc = from_opendrive(p, n_frames=3, **BARE)
    # left lane (3.0 m) on the inside of a left turn, right lane (3.5 m) outside
    expect = theta / 2 * (R ** 2 - (R - 3.0) ** 2) + theta / 2 * ((R + 3.5) ** 2 - R ** 2)
    assert sc.meta["road_length"] == pytest.approx(L)
    assert sc.meta["road_area"] == pytest.approx(expect, rel=0.01)
    road = parse_opendrive(p).roads[0]
    x, y, h = road.reference(np.array([L]))
    assert x[0] == pytest.approx(R, abs=1e-9) and y[0] == pytest.approx(R, abs=1e-9)
    assert h[0] == pytest.approx(theta)


def test_spiral_matches_fresnel(tmp_path):
    L, k1 = 60.0, 0.04
    p = write(tmp_path, road_xml(0, L, geom(L, f'<spiral curvStart="0" curvEnd="{k1!r}"/>')))
    road = parse_opendrive(p).roads[0]
    c = k1 / L
    S, Cf = fresnel(L * math.sqrt(c / math.pi))
    x, y, h = road.reference(np.array([L]))
    assert x[0] == pytest.approx(math.sqrt(math.pi / c) * Cf, abs=1e-4)
    assert y[0] == pytest.approx(math.sqrt(math.pi / c) * S, abs=1e-4)
    assert h[0] == pytest.approx(0.5 * k1 * L)
    sc = from_opendrive(p, n_frames=2, **BARE)
    assert sc.meta["road_area"] == pytest.approx(6.5 * L, rel=0.01)


def test_poly3_arc_length(tmp_path):
    c, L = 0.01, 40.0
    p = write(tmp_path, road_xml(0, L, geom(L, f'<poly3 a="0" b="0" c="{c!r}" d="0"/>', hdg=0.3, x=5.0, y=-2.0)))
    road = parse_opendrive(p).roads[0]
    x, y, h = road.reference(np.array([L]))
    ch, sh = math.cos(0.3), math.sin(0.3)
    u = ch * (x[0] - 5.0) + sh * (y[0] + 2.0)
    v = -sh * (x[0] - 5.0) + ch * (y[0] + 2.0)
    assert v == pytest.approx(c * u * u, abs=1e-4)  # on the curve (table interpolation)
    arc = u * math.sqrt(1 + 4 * c * c * u * u) / 2 + math.asinh(2 * c * u) / (4 * c)
    assert arc == pytest.approx(L, rel=1e-4)  # at arc length L
    assert h[0] == pytest.approx(0.3 + math.atan(2 * c * u), abs=1e-4)


def test_parampoly3_both_ranges(tmp_path):
    L = 30.0
    # normalized: u = L p^3 (non-uniform speed), v = 0 -> a straight line; s must map to x = s
    g1 = geom(L, f'<paramPoly3 aU="0" bU="0" cU="0" dU="{L!r}" aV="0" bV="0" cV="0" dV="0" pRange="normalized"/>')
    # arcLength: u = p, v = 0.5 p^2 / 30
    g2 = geom(L, '<paramPoly3 aU="0" bU="1" cU="0" dU="0" aV="0" bV="0" cV="0.0166666667" dV="0" pRange="arcLength"/>')
    p = write(tmp_path, road_xml(0, L, g1), road_xml(1, L, g2))
    r1, r2 = parse_opendrive(p).roads
    x, y, _ = r1.reference(np.array([7.5, 15.0]))
    assert np.allclose(x, [7.5, 15.0], atol=0.02) and np.allclose(y, 0.0)
    x, y, h = r2.reference(np.array([L]))
    assert x[0] == pytest.approx(30.0) and y[0] == pytest.approx(15.0, rel=1e-6)
    assert h[0] == pytest.approx(math.atan(1.0), abs=1e-3)


def test_elevation_and_lane_offset(tmp_path):
    lanes = lanes_xml(extra='<laneOffset s="0" a="1.0" b="0" c="0" d="0"/>')
    p = write(tmp_path, road_xml(0, 50.0, geom(50.0, "<line/>"), lanes,
                                 elevation='<elevation s="0" a="2.0" b="0.1" c="0" d="0"/>'))
    sc = from_opendrive(p, n_frames=4, **BARE)
    v = sc.static.vertices
    assert v[:, 2].min() == pytest.approx(2.0) and v[:, 2].max() == pytest.approx(7.02)
    assert v[:, 1].min() == pytest.approx(1.0 - 3.5) and v[:, 1].max() == pytest.approx(4.0)
    e = sc.ego_poses
    assert np.allclose(e[:, 2], 2.0 + 0.1 * e[:, 0], atol=1e-6)
    assert np.allclose(e[:, 4], -math.atan(0.1))  # nose up on the climb
    assert np.allclose(e[:, 1], 1.0 - 1.75)


def test_junction_lengths_and_route(tmp_path):
    """Two roads joined through a junction of one connecting road: lengths add, the ego drives through."""
    R = 10.0
    L1 = 40.0
    arc = R * math.pi / 2
    one = lanes_xml(left=(), right=(("driving", 3.5),), center_mark="none")
    roads = [road_xml(0, L1, geom(L1, "<line/>"), one),
             road_xml(1, arc, geom(arc, f'<arc curvature="{1 / R!r}"/>', x=L1), one, junction="1"),
             road_xml(2, L1, geom(L1, "<line/>", x=L1 + R, y=R, hdg=math.pi / 2), one)]
    junc = '<junction id="1" name="j"><connection id="0" incomingRoad="0" connectingRoad="1" contactPoint="start"/></junction>'
    p = write(tmp_path, *roads, junctions=junc)
    sc = from_opendrive(p, n_frames=30, ego_speed=6.0, **BARE)
    assert sc.meta["road_length"] == pytest.approx(2 * L1 + arc)
    assert sc.meta["road_length_no_junction"] == pytest.approx(2 * L1)
    assert sc.meta["n_junctions"] == 1
    expect = 3.5 * L1 * 2 + math.pi / 4 * ((R + 3.5) ** 2 - R ** 2)
    assert sc.meta["road_area"] == pytest.approx(expect, rel=0.01)
    # 30 frames at 6 m/s cover 87 m: the route turns through the junction onto road 2
    end = sc.ego_poses[-1]
    assert end[0] > L1 + R and end[5] == pytest.approx(math.pi / 2, abs=0.05)


def test_roadside_traffic_seeded(tmp_path):
    lanes = lanes_xml(left=(("driving", 3.5), ("sidewalk", 3.0)), right=(("driving", 3.5), ("sidewalk", 3.0)))
    p = write(tmp_path, road_xml(0, 300.0, geom(300.0, "<line/>"), lanes))
    a = from_opendrive(p, seed=3, n_frames=10, n_traffic=3, n_pedestrians=3)
    b = from_opendrive(p, seed=3, n_frames=10, n_traffic=3, n_pedestrians=3)
    assert a.key == b.key and np.array_equal(a.static.vertices, b.static.vertices)
    assert len(a.actors) == len(b.actors) and len(a.actors) >= 1
    labs = set(a.static.labels.tolist())
    assert {6, 7, 8, 21} <= labs and labs & {1, 5, 9}  # roadside content exists
    # nothing besides lane surfaces and lines lies over the carriageway (|y| < 3.5)
    v, f, lab = a.static.vertices, a.static.faces, a.static.labels
    cen = v[f].mean(axis=1)
    over = (np.abs(cen[:, 1]) < 3.4) & (cen[:, 0] > 1) & (cen[:, 0] < 299) & (cen[:, 2] < 3.0)  # arms may overhang
    assert set(lab[over].tolist()) <= {6, 7, 21}
    for act in a.actors:
        if act.kind == "vehicle":
            assert np.all(np.abs(act.poses[:, 1]) < 3.5)


@pytest.mark.parametrize("bad, msg", [
    ("<OpenDRIVE><road", "not well-formed XML"),
    ("<Other/>", "expected <OpenDRIVE>"),
    ("<OpenDRIVE><header/></OpenDRIVE>", "no <road>"),
    ('<OpenDRIVE><road id="7" length="10"><lanes/></road></OpenDRIVE>', "road 7 has no <planView>"),
    ('<OpenDRIVE><road id="7" length="10"><planView><geometry s="0" x="0" y="0" hdg="0" length="10"/>'
     '</planView><lanes/></road></OpenDRIVE>', "has no line/arc"),
    ('<OpenDRIVE><road id="7" length="10"><planView><geometry s="0" x="zero" y="0" hdg="0" length="10"><line/>'
     '</geometry></planView><lanes/></road></OpenDRIVE>', "is not a number"),
    ('<OpenDRIVE><road id="7" length="10"><planView><geometry s="0" x="0" y="0" hdg="0" length="10"><arc/>'
     '</geometry></planView><lanes/></road></OpenDRIVE>', "missing attribute 'curvature'"),
    ('<OpenDRIVE><road id="7" length="10"><planView><geometry s="0" x="0" y="0" hdg="0" length="10"><line/>'
     '</geometry></planView></road></OpenDRIVE>', "has no <lanes>"),
    ('<OpenDRIVE><road id="7" length="10"><planView><geometry s="0" x="0" y="0" hdg="0" length="10"><line/>'
     '</geometry></planView><lanes><laneSection s="0"><right><lane id="-1" type="driving"/></right>'
     '</laneSection></lanes></road></OpenDRIVE>', "neither <width> nor <border>"),
    ('<OpenDRIVE><road id="7" length="-1"><planView/></road></OpenDRIVE>', "non-positive length"),
])
def test_malformed_files(tmp_path, bad, msg):
    p = tmp_path / "bad.xodr"
    p.write_text(bad)
    with pytest.raises(ValueError, match=msg) as e:
        from_opendrive(p)
    assert "bad.xodr" in str(e.value)


def test_missing_file_and_bad_options(tmp_path):
    with pytest.raises(ValueError, match="no such OpenDRIVE file"):
        from_opendrive(tmp_path / "nope.xodr")
    p = write(tmp_path, road_xml(0, 10.0, geom(10.0, "<line/>")))
    with pytest.raises(ValueError, match="unknown from_opendrive options"):
        from_opendrive(p, colour="red")


@pytest.mark.parametrize("town", sorted(TOWN_LENGTHS))
def test_carla_town_builds_and_evaluates(town):
    path = opendrive_path(town)
    sc = from_opendrive(path, seed=0, n_frames=4)  # build time is measured in bench/, not asserted here
    assert sc.name == f"opendrive-{town}"
    assert sc.meta["road_length"] / 1000 == pytest.approx(TOWN_LENGTHS[town], rel=0.015)
    assert sc.meta["road_area"] > 1e4
    labs = set(sc.static.labels.tolist())
    assert {6, 7, 21, 10} <= labs
    lidar = p3k.LidarModel.uniform(16, (-30, 10), 256, max_range=60)
    from place3d_kernels.simulate import simulate

    frames = simulate(sc, lidar)
    assert all(len(f.points) > 1000 for f in frames)
    lab = np.concatenate([f.labels for f in frames])
    assert np.mean(np.isin(lab, [6, 7])) > 0.2  # the ego sees its road
    grid = p3k.Grid(lower=(-30, -30, -1), upper=(30, 30, 5), voxel_size=1.0)
    psog = p3k.PSOG.from_frames(frames, grid, frames_per_subset=2)
    placement = p3k.Placement.load("pyramid")
    score = p3k.msog(psog, lidar, placement)
    assert np.isfinite(score) and score <= 0.0


# one low-poly car is about 100 triangles (two boxes, four 6-sided wheels): 150 means more than one vehicle
# (the lead and at least one parked or passing car) within 40 m of the ego at every checked frame
MIN_VEHICLE_TRIANGLES = 150


@pytest.mark.parametrize("town", sorted(TOWN_LENGTHS))
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_carla_town_has_vehicles_near_the_ego(town, seed):
    path = opendrive_path(town)
    sc = from_opendrive(path, seed=seed, n_frames=40)
    assert sum(a.kind == "vehicle" for a in sc.actors) > 0 and sc.meta["n_parked"] > 0
    for f in (0, sc.n_frames // 2, sc.n_frames - 1):
        m = sc.mesh(f)
        centre = m.vertices[m.faces].mean(axis=1)[:, :2]
        near = np.linalg.norm(centre - sc.ego_poses[f, :2], axis=1) < 40.0
        n_vehicle = int(np.sum(near & (m.labels == CLASS_ID["vehicle"])))
        assert n_vehicle >= MIN_VEHICLE_TRIANGLES, (town, seed, f, n_vehicle)


def test_builder_version_is_part_of_the_key(tmp_path):
    p = write(tmp_path, road_xml(0, 30.0, geom(30.0, "<line/>")))
    a = from_opendrive(p, n_frames=2, **BARE)
    b = from_opendrive(p, n_frames=2, **BARE)
    assert a.meta["builder"].startswith("opendrive-") and a.key == b.key
    b.meta["builder"] = "opendrive-older"
    b.__dict__.pop("_key", None)
    assert a.key != b.key


def test_routes_of_a_town_share_its_roads_and_match_a_fresh_build(tmp_path):
    from place3d_kernels.scene import opendrive

    lanes = lanes_xml(left=(("driving", 3.5), ("sidewalk", 3.0)), right=(("driving", 3.5), ("sidewalk", 3.0)))
    p = write(tmp_path, road_xml(0, 200.0, geom(200.0, "<line/>"), lanes))
    kw = dict(n_frames=6, n_traffic=2, n_pedestrians=2)
    opendrive._BASES.clear()
    from_opendrive(p, seed=0, **kw)
    shared = from_opendrive(p, seed=1, **kw)                # the roads of seed 0's build, reused
    assert len(opendrive._BASES) == 1
    opendrive._BASES.clear()
    fresh = from_opendrive(p, seed=1, **kw)
    assert shared.key == fresh.key
    for a, b in ((shared.static.vertices, fresh.static.vertices), (shared.static.faces, fresh.static.faces),
                 (shared.static.labels, fresh.static.labels), (shared.ego_poses, fresh.ego_poses)):
        assert np.array_equal(a, b)
    assert [a.poses.tobytes() for a in shared.actors] == [a.poses.tobytes() for a in fresh.actors]
    (base,) = opendrive._BASES.values()
    with pytest.raises(ValueError, match="read-only"):      # what every route reads, none may change
        base.parts[0][0][0, 0] = 1.0
    # the file rewritten with another road: another town
    write(tmp_path, road_xml(0, 120.0, geom(120.0, "<line/>"), lanes))
    other = from_opendrive(p, seed=1, **kw)
    assert len(opendrive._BASES) == 2 and other.meta["road_length"] == pytest.approx(120.0)
