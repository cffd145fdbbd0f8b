"""Mitsuba XML scenes without Mitsuba: transforms, primitives, labels, $variables, errors, and (when
Mitsuba 3 is importable) a cross-check of area and bounds against ``mitsuba.load_file``."""

from __future__ import annotations

import math

import numpy as np
import pytest

from place3d_kernels.mesh import Mesh
from place3d_kernels.scene import Scene
from place3d_kernels.scene.loaders import save_mesh
from place3d_kernels.scene.mitsuba_xml import load_mitsuba_scene, load_mitsuba_xml

# an asymmetric tetrahedron: every transform shows in its vertices
TET_V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 3.0]])
TET_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def write_ply(path, v=TET_V, f=TET_F):
    import trimesh

    trimesh.Trimesh(v, f, process=False).export(path)
    return path


def write_xml(tmp_path, body, name="scene.xml"):
    p = tmp_path / name
    p.write_text(f'<?xml version="1.0"?>\n<scene version="3.0.0">\n{body}\n</scene>\n')
    return p


def rot(axis, deg):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    t = math.radians(deg)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K


def area(m: Mesh) -> float:
    v, f = m.vertices, m.faces
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()


def ply_shape(fn, transform="", extra="", sid="t"):
    return (f'<shape type="ply" id="{sid}"><string name="filename" value="{fn}"/>{extra}'
            f'<transform name="to_world">{transform}</transform></shape>')


@pytest.mark.parametrize("transform, expect", [
    ('<translate x="1" y="-2" z="3"/>', lambda v: v + (1, -2, 3)),
    ('<translate value="1, -2, 3"/>', lambda v: v + (1, -2, 3)),
    ('<scale value="2"/>', lambda v: v * 2),
    ('<scale x="2" y="3"/>', lambda v: v * (2, 3, 1)),
    ('<rotate z="1" angle="90"/>', lambda v: v @ rot((0, 0, 1), 90).T),
    ('<rotate value="0.6 0.8 0" angle="30"/>', lambda v: v @ rot((0.6, 0.8, 0), 30).T),
    ('<rotate axis="0 1 0" angle="-45"/>', lambda v: v @ rot((0, 1, 0), -45).T),
    # document order: scale, then rotate, then translate (each left-multiplies)
    ('<scale value="2 1 1"/><rotate z="1" angle="90"/><translate x="5"/>',
     lambda v: (v * (2, 1, 1)) @ rot((0, 0, 1), 90).T + (5, 0, 0)),
    ('<translate x="5"/><rotate z="1" angle="90"/>', lambda v: (v + (5, 0, 0)) @ rot((0, 0, 1), 90).T),
    ('<matrix value="0 -1 0 4  1 0 0 5  0 0 2 6  0 0 0 1"/>',
     lambda v: v @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 2]]).T + (4, 5, 6)),
    ('<lookat origin="1 2 3" target="1 2 4" up="0 1 0"/>',  # z -> +z, y -> up, x -> left = up x dir
     lambda v: v @ np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]]).T + (1, 2, 3)),
    ('<lookat origin="0 0 0" target="1 0 0" up="0 0 1"/>',
     lambda v: v @ np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]]).T),
])
def test_transforms_match_numpy(tmp_path, transform, expect):
    write_ply(tmp_path / "tet.ply")
    m = load_mitsuba_xml(write_xml(tmp_path, ply_shape("tet.ply", transform)))
    assert np.array_equal(m.faces, TET_F)
    assert np.allclose(m.vertices, expect(TET_V), atol=1e-12)


def test_non_unit_rotation_axis_is_used_as_given_like_mitsuba(tmp_path):
    write_ply(tmp_path / "tet.ply")
    p = write_xml(tmp_path, ply_shape("tet.ply", '<rotate value="1 2 3" angle="37"/>'))
    with pytest.warns(UserWarning, match="not unit length"):
        m = load_mitsuba_xml(p)
    a, c, s = np.array([1.0, 2, 3]), math.cos(math.radians(37)), math.sin(math.radians(37))
    K = np.array([[0, -3, 2], [3, 0, -1], [-2, 1, 0]])
    R = c * np.eye(3) + (1 - c) * np.outer(a, a) + s * K
    assert np.allclose(m.vertices, TET_V @ R.T)
    assert np.allclose(m.vertices[1], (1.0, 2.2082, -0.5995), atol=1e-4)  # what Mitsuba 3.9 gives


def test_filenames_relative_to_the_xml_and_several_shapes(tmp_path):
    (tmp_path / "meshes").mkdir()
    (tmp_path / "sub").mkdir()
    write_ply(tmp_path / "meshes" / "tet.ply")
    body = (ply_shape("../meshes/tet.ply", '<translate x="10"/>', sid="a")
            + ply_shape("../meshes/tet.ply", '<translate x="-10"/>', sid="b"))
    m = load_mitsuba_xml(write_xml(tmp_path / "sub", body))
    assert m.n_faces == 8 and len(m.vertices) == 8
    assert np.allclose(m.vertices[:4], TET_V + (10, 0, 0)) and np.allclose(m.vertices[4:], TET_V - (10, 0, 0))


def test_primitives_extents_and_area(tmp_path):
    body = """
    <shape type="rectangle" id="r"><transform name="to_world"><scale x="3" y="2"/><translate z="1"/></transform></shape>
    <shape type="cube" id="c"><transform name="to_world"><scale value="0.5"/><translate x="10"/></transform></shape>
    <shape type="sphere" id="s"><point name="center" x="0" y="20" z="0"/><float name="radius" value="2"/></shape>
    <shape type="disk" id="d"><transform name="to_world"><translate z="-5"/></transform></shape>
    <shape type="cylinder" id="y"><point name="p0" value="0 0 0"/><point name="p1" value="0 0 4"/>
        <float name="radius" value="0.5"/><transform name="to_world"><translate x="-20"/></transform></shape>
    """
    p = write_xml(tmp_path, body)
    m = load_mitsuba_xml(p, labels={"r": "road", "c": "building", "s": "vegetation", "d": 11, "y": "pole"})
    by = {c: m.vertices[np.unique(m.faces[m.labels == c])] for c in np.unique(m.labels)}
    rect, cube, sph, pole = by[7], by[1], by[9], by[5]
    assert np.allclose(rect.min(0), (-3, -2, 1)) and np.allclose(rect.max(0), (3, 2, 1))
    assert (m.labels == 7).sum() == 2 and (m.labels == 1).sum() == 12
    assert np.allclose(cube.min(0), (9.5, -0.5, -0.5)) and np.allclose(cube.max(0), (10.5, 0.5, 0.5))
    assert np.allclose(np.linalg.norm(sph - (0, 20, 0), axis=1), 2.0)
    assert (m.labels == 9).sum() == 20 * 4 ** 3
    r = lambda c: 0.5 * np.linalg.norm(np.cross(*(m.vertices[m.faces[m.labels == c]][:, 1:] -
                                                   m.vertices[m.faces[m.labels == c]][:, :1]).transpose(1, 0, 2)),
                                       axis=1).sum()
    assert r(7) == pytest.approx(24.0) and r(1) == pytest.approx(6.0)
    assert r(9) == pytest.approx(4 * math.pi * 4, rel=0.02)
    assert r(11) == pytest.approx(math.pi, rel=0.01)
    assert r(5) == pytest.approx(2 * math.pi * 0.5 * 4, rel=0.01)
    assert np.allclose(pole.min(0), (-20.5, -0.5, 0), atol=1e-9) and np.isclose(pole[:, 2].max(), 4)


def test_labels_by_id_bsdf_stem_class_names_and_fallback(tmp_path):
    write_ply(tmp_path / "tet.ply")
    write_ply(tmp_path / "tree.ply")
    body = """
    <bsdf type="twosided" id="asphalt"><bsdf type="diffuse" id="asphalt_inner"/></bsdf>
    <bsdf type="diffuse" id="sidewalk"/>
    <bsdf type="diffuse" id="misc"/>
    <shape type="ply" id="a"><string name="filename" value="tet.ply"/><ref id="asphalt"/></shape>
    <shape type="ply" id="b"><string name="filename" value="tet.ply"/><ref id="sidewalk"/></shape>
    <shape type="ply" id="vehicle_01"><string name="filename" value="tet.ply"/><ref id="misc"/></shape>
    <shape type="ply"><string name="filename" value="tree.ply"/></shape>
    <shape type="rectangle" id="x"><bsdf type="diffuse" id="inline_mat"/></shape>
    <shape type="cube"/>
    """
    p = write_xml(tmp_path, body)
    m = load_mitsuba_xml(p, labels={"asphalt": "road", "a": "building", "tree": "vegetation",
                                    "inline_mat": "terrain", "*": "static"})
    per = [int(m.labels[i]) for i in (0, 4, 8, 12, 16, 18)]
    # shape id beats bsdf id; bsdf id "sidewalk" and shape id "vehicle_01" are class names; stem "tree" is mapped;
    # an inline bsdf id is mapped; the unnamed cube falls back to "*"
    assert per == [1, 8, 10, 9, 21, 18]
    m = load_mitsuba_xml(p, labels={"asphalt_inner": "road"})
    assert int(m.labels[0]) == 7 and int(m.labels[-1]) == 0
    m = load_mitsuba_xml(p, labels="building")
    assert set(m.labels.tolist()) == {1}
    toml = tmp_path / "labels.toml"
    toml.write_text('[labels]\nasphalt = "road"\n"*" = 18\n')
    m = load_mitsuba_xml(p, labels=toml, default="terrain")
    assert int(m.labels[0]) == 7 and int(m.labels[-1]) == 18


def test_per_face_ply_labels_survive_when_nothing_maps_the_shape(tmp_path):
    from place3d_kernels.scene.primitives import boxes

    v, f = boxes([(0, 0, 0), (4, 0, 0)], [(1, 1, 1), (1, 1, 1)])
    save_mesh(Mesh(v, f, np.repeat([7, 10], 12)), tmp_path / "lab.ply")
    p = write_xml(tmp_path, '<shape type="ply" id="thing"><string name="filename" value="lab.ply"/></shape>')
    assert np.array_equal(load_mitsuba_xml(p).labels, np.repeat([7, 10], 12))
    assert set(load_mitsuba_xml(p, labels={"thing": 12}).labels.tolist()) == {12}


def test_default_variables_and_overrides(tmp_path):
    write_ply(tmp_path / "tet.ply")
    body = """
    <default name="mesh" value="tet"/>
    <default name="dx" value="7"/>
    <default name="ang" value="90"/>
    <shape type="ply" id="$mesh"><string name="filename" value="$mesh.ply"/>
      <transform name="to_world"><rotate z="1" angle="$ang"/><translate x="$dx" y="1"/></transform></shape>
    """
    p = write_xml(tmp_path, body)
    m = load_mitsuba_xml(p, labels={"tet": "road"})
    assert np.allclose(m.vertices, TET_V @ rot((0, 0, 1), 90).T + (7, 1, 0)) and set(m.labels.tolist()) == {7}
    m = load_mitsuba_xml(p, variables={"dx": -3, "ang": "0"})
    assert np.allclose(m.vertices, TET_V + (-3, 1, 0))


def test_include_shapegroup_instance_and_flip_normals(tmp_path):
    write_ply(tmp_path / "tet.ply")
    write_xml(tmp_path, ply_shape("tet.ply", '<translate z="$h"/>', sid="inc"), name="part.xml")
    body = """
    <default name="h" value="2"/>
    <include filename="part.xml"/>
    <shape type="shapegroup" id="grp">
      <shape type="ply" id="g"><string name="filename" value="tet.ply"/>
        <boolean name="flip_normals" value="true"/></shape>
    </shape>
    <shape type="instance"><ref id="grp"/><transform name="to_world"><translate x="100"/></transform></shape>
    <shape type="instance"><ref id="grp"/><transform name="to_world"><translate x="200"/></transform></shape>
    """
    m = load_mitsuba_xml(write_xml(tmp_path, body))
    assert m.n_faces == 12
    assert np.allclose(m.vertices[:4], TET_V + (0, 0, 2))
    assert np.allclose(m.vertices[4:8], TET_V + (100, 0, 0)) and np.allclose(m.vertices[8:], TET_V + (200, 0, 0))
    assert np.array_equal(m.faces[4:8] - 4, TET_F[:, ::-1])


def test_unsupported_shapes_warn_and_are_skipped(tmp_path):
    body = """
    <shape type="serialized" id="old"><string name="filename" value="x.serialized"/></shape>
    <shape type="bsplinecurve" id="hair"/>
    <shape type="rectangle"/>
    <sensor type="perspective"><transform name="to_world">
      <lookat origin="0 0 5" target="0 0 0" up="0 1 0"/></transform></sensor>
    <emitter type="constant"/>
    """
    with pytest.warns(UserWarning, match=r"old \(type 'serialized'\).*hair \(type 'bsplinecurve'\)"):
        m = load_mitsuba_xml(write_xml(tmp_path, body))
    assert m.n_faces == 2


def test_scene_wrapper_mirrors_load_scene(tmp_path):
    p = write_xml(tmp_path, '<shape type="cube" id="building"/>')
    s = load_mitsuba_scene(p)
    assert isinstance(s, Scene) and s.name == "mitsuba-scene" and s.ego_poses.shape == (1, 6)
    assert np.all(s.ego_poses == 0) and set(s.static.labels.tolist()) == {1}
    s = load_mitsuba_scene(p, ego_poses=[[1, 2, 0, 0, 0, 0], [2, 2, 0, 0, 0, 0]])
    assert s.ego_poses.shape == (2, 6)


@pytest.mark.parametrize("body, match", [
    ('<shape type="cube"', r"scene\.xml: malformed XML"),
    ('<shape type="ply" id="m"><string name="filename" value="nope.ply"/></shape>',
     r"scene\.xml: shape 'm' \(type 'ply'\): file 'nope.ply' not found"),
    ('<shape type="ply" id="m"/>', r"scene\.xml: shape 'm' \(type 'ply'\) has no <string name='filename'>"),
    ('<shape type="cube"><transform name="to_world"><shear value="1"/></transform></shape>',
     r"scene\.xml: .*unknown transform <shear>"),
    ('<shape type="cube"><transform name="to_world"><translate value="1 2"/></transform></shape>',
     r"scene\.xml: .*<translate>.*expected 1 or 3 numbers"),
    ('<shape type="cube"><transform name="to_world"><rotate angle="9"/></transform></shape>',
     r"scene\.xml: .*<rotate> has no rotation axis"),
    ('<shape type="cube"><transform name="to_world"><matrix value="1 0 0 1"/></transform></shape>',
     r"scene\.xml: .*<matrix> value: expected 9 or 16 numbers"),
    ('<shape type="cube"><transform name="to_world"><scale value="a"/></transform></shape>',
     r"scene\.xml: .*'a' is not a list of numbers"),
    ('<shape type="cube" id="$undefined"/>', r"scene\.xml: <shape> uses \$undefined, which has no <default>"),
    ('<shape type="cube"><ref id="ghost"/></shape>', r"scene\.xml: <ref id='ghost'>.*names no element"),
    ('<include filename="other.xml"/>', r"scene\.xml: include file 'other.xml' not found"),
    ('<emitter type="constant"/>', r"scene\.xml: holds no supported shapes"),
])
def test_errors_name_the_file_and_problem(tmp_path, body, match):
    p = write_xml(tmp_path, body)
    with pytest.raises(ValueError, match=match):
        load_mitsuba_xml(p)


def test_other_errors(tmp_path):
    with pytest.raises(ValueError, match=r"missing\.xml: no such Mitsuba XML file"):
        load_mitsuba_xml(tmp_path / "missing.xml")
    p = tmp_path / "notscene.xml"
    p.write_text("<bsdf type='diffuse'/>")
    with pytest.raises(ValueError, match=r"notscene\.xml: the root element is <bsdf>"):
        load_mitsuba_xml(p)
    (tmp_path / "bad.ply").write_text("ply\nnonsense\n")
    p = write_xml(tmp_path, '<shape type="ply"><string name="filename" value="bad.ply"/></shape>')
    with pytest.raises(ValueError, match=r"bad\.ply: cannot read as PLY"):
        load_mitsuba_xml(p)
    p = write_xml(tmp_path, '<shape type="cube" id="c"/>')
    with pytest.raises(ValueError, match="unknown class name 'bogus'"):
        load_mitsuba_xml(p, labels={"c": "bogus"})


# ------------------------------------------------------------------------------------- cross-check
def _mitsuba():
    try:
        import mitsuba as mi

        mi.set_variant("scalar_rgb")
        return mi
    except Exception as e:  # noqa: BLE001 - any import / variant failure skips
        pytest.skip(f"Mitsuba 3 unavailable ({type(e).__name__}: {e})")


def test_cross_check_against_mitsuba(tmp_path):
    mi = _mitsuba()
    write_ply(tmp_path / "tet.ply")
    write_ply(tmp_path / "tet2.ply", TET_V * 2)
    import trimesh

    trimesh.Trimesh(TET_V, TET_F, process=False).export(tmp_path / "tet.obj")
    body = """
    <default name="s" value="1.5"/>
    <bsdf type="diffuse" id="mat"/>
    """ + ply_shape("tet.ply",
                    '<scale value="$s"/><rotate value="0.48 0.6 0.64" angle="37"/><translate value="1 2 3"/>',
                    '<ref id="mat"/>', sid="a") + ply_shape(
        "tet2.ply", '<matrix value="0.5 0.2 0 -4  0 1 0.3 2  0.1 0 2 1  0 0 0 1"/><rotate x="1" angle="20"/>',
        sid="b") + """
    <shape type="obj" id="o"><string name="filename" value="tet.obj"/>
      <transform name="to_world"><lookat origin="3 -4 1" target="5 0 2" up="0 0 1"/></transform></shape>
    <shape type="rectangle" id="r"><transform name="to_world"><scale x="4" y="2"/><rotate z="1" angle="30"/>
      <translate value="0 0 -1"/></transform></shape>
    <shape type="cube" id="c"><transform name="to_world"><scale value="0.5 1 2"/><rotate y="1" angle="-60"/>
      <translate value="6 -3 0"/></transform></shape>
    """
    p = write_xml(tmp_path, body)
    ours = load_mitsuba_xml(p)
    scene = mi.load_file(str(p))
    their_area = sum(float(s.surface_area()[0] if hasattr(s.surface_area(), "__len__") else s.surface_area())
                     for s in scene.shapes())
    assert area(ours) == pytest.approx(their_area, rel=1e-5)
    bb = scene.bbox()
    assert np.allclose(ours.bounds[0], np.array(bb.min, float), atol=1e-4)
    assert np.allclose(ours.bounds[1], np.array(bb.max, float), atol=1e-4)
    # per-shape vertices against Mitsuba's own (PLY keeps the vertex order; Mitsuba's OBJ reader reorders)
    shapes = {s.id(): s for s in scene.shapes()}
    for sid, o in {"a": 0, "b": 4, "o": 8}.items():
        mv = np.array(shapes[sid].vertex_positions_buffer(), float).reshape(-1, 3)
        mine = ours.vertices[o:o + 4]
        if sid == "o":
            mine, mv = mine[np.lexsort(mine.T)], mv[np.lexsort(mv.T)]
        assert np.allclose(mine, mv, atol=1e-5), sid


def test_unlabelled_shapes_warn_with_their_count_and_the_fix(tmp_path):
    # a Mitsuba scene without --labels turned 2,365 buildings into class 0 without a word (an OBJ warns)
    import warnings

    write_ply(tmp_path / "tet.ply")
    body = (ply_shape("tet.ply", '<translate x="10"/>', sid="house_1") + ply_shape("tet.ply", "", sid="house_2")
            + '<shape type="cube" id="road"/>' + '<shape type="rectangle"/>')
    p = write_xml(tmp_path, body)
    with pytest.warns(UserWarning, match=r"3 of 4 shapes match no label rule and become class 0 \(unlabeled\): "
                                         r"\(rectangle, no id\), house_1, house_2; .*--labels"):
        m = load_mitsuba_xml(p)
    assert sorted(set(m.labels.tolist())) == [0, 7]                    # the class-named cube is a road
    # labelled, fully or by '*', or with an explicit default: no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_mitsuba_xml(p, labels={"*": "building"})
        load_mitsuba_xml(p, labels="building")
        load_mitsuba_xml(p, default="static")
        load_mitsuba_scene(p, labels={"house_1": 1, "house_2": 1, "*": 0})
    # a partial map warns for the rest only
    with pytest.warns(UserWarning, match=r"1 of 4 shapes .*\(rectangle, no id\)"):
        load_mitsuba_xml(p, labels={"house_1": 1, "house_2": "building"})
