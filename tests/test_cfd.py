"""CFD meshes: labelled caps, flow extensions, volume meshes, boundary layers, files, quality measures."""

from __future__ import annotations

import json

import meshio
import numpy as np
import pytest

import vesselcad as vc
from vesselcad.cfd import RadiusField, aspect_ratio, scaled_jacobian
from vesselcad.cli import main


def _line(p0, d, length, n=30):
    d = np.asarray(d, float) / np.linalg.norm(d)
    return np.asarray(p0, float) + np.linspace(0.0, length, n)[:, None] * d


def _tree(branches):
    return vc.VesselTree.from_json({"units": "mm", "frame": "LPS", "branches": branches})


AXIS = np.array([1.0, 2.0, 2.0]) / 3.0
START = np.array([1.0, 2.0, 3.0])
R_TUBE, L_TUBE = 1.5, 30.0

# A Y: parent r = 2 along z from 0 to 20, children r = 1.4 at +-25 deg, 25 mm long. The
# parent continues into the left child within 30 deg, so the tree merges into two vessels:
# one inlet (parent start) and two outlets (children ends).
ANGLE = np.radians(25.0)
LEFT = np.array([np.sin(ANGLE), 0.0, np.cos(ANGLE)])
RIGHT = np.array([-np.sin(ANGLE), 0.0, np.cos(ANGLE)])
JOIN = np.array([0.0, 0.0, 20.0])


@pytest.fixture(scope="module")
def tube_solid():
    return _tree([{"id": 0, "parent": None, "points": _line(START, AXIS, L_TUBE).tolist(),
                   "radius": [R_TUBE] * 30}]).solid()


@pytest.fixture(scope="module")
def y_tree():
    return _tree([
        {"id": 0, "parent": None, "name": "main", "points": _line([0, 0, 0], [0, 0, 1], 20).tolist(),
         "radius": [2.0] * 30},
        {"id": 1, "parent": 0, "name": "left", "points": _line(JOIN, LEFT, 25).tolist(),
         "radius": [1.4] * 30},
        {"id": 2, "parent": 0, "name": "right", "points": _line(JOIN, RIGHT, 25).tolist(),
         "radius": [1.4] * 30},
    ])


@pytest.fixture(scope="module")
def y_solid(y_tree):
    return y_tree.solid()


@pytest.fixture(scope="module")
def y_volume(y_solid):
    return vc.cfd.volume_mesh(y_solid, edge_factor=0.4)


def test_straight_tube_surface_has_one_inlet_and_one_outlet_of_area_pi_r2(tube_solid):
    surf = vc.cfd.surface_mesh(tube_solid)
    bnds = surf.metadata["boundaries"]
    assert [b["name"] for b in bnds] == ["inlet", "outlet_1"]
    area = np.pi * R_TUBE**2
    for b in bnds:
        assert b["area_mm2"] == pytest.approx(area, rel=0.01)
        assert b["exact_area_mm2"] == pytest.approx(area, rel=1e-4)
    inlet, outlet = bnds
    assert np.allclose(inlet["centre"], START, atol=1e-3)
    assert np.allclose(outlet["centre"], START + L_TUBE * AXIS, atol=1e-3)
    assert np.allclose(inlet["normal"], -AXIS, atol=1e-6)
    assert np.allclose(outlet["normal"], AXIS, atol=1e-6)
    # the labelled facets: their areas are the reported ones, the wall is 2 pi r L
    labels = surf.face_attributes["label"]
    assert set(np.unique(labels)) == {vc.cfd.WALL_ID, vc.cfd.INLET_ID, vc.cfd.INLET_ID + 1}
    assert surf.area_faces[labels == vc.cfd.INLET_ID].sum() == pytest.approx(inlet["area_mm2"], rel=1e-6)
    assert surf.area_faces[labels == vc.cfd.WALL_ID].sum() == pytest.approx(2 * np.pi * R_TUBE * L_TUBE,
                                                                             rel=0.01)
    assert surf.is_watertight and surf.is_winding_consistent
    assert surf.volume == pytest.approx(area * L_TUBE, rel=0.02)  # > 0: outward
    # element size follows the radius: edges about 0.3 r
    edges = surf.edges_unique_length
    assert 0.2 * R_TUBE < np.median(edges) < 0.4 * R_TUBE


def test_y_bifurcation_has_one_inlet_and_two_outlets(y_solid):
    surf = vc.cfd.surface_mesh(y_solid)
    bnds = surf.metadata["boundaries"]
    assert [b["role"] for b in bnds] == ["inlet", "outlet", "outlet"]
    assert [b["name"] for b in bnds] == ["inlet", "outlet_1", "outlet_2"]
    inlet = bnds[0]
    assert np.allclose(inlet["centre"], [0, 0, 0], atol=1e-3)
    assert inlet["area_mm2"] == pytest.approx(np.pi * 4.0, rel=0.01)
    ends = {tuple(np.round(JOIN + 25 * d, 3)): d for d in (LEFT, RIGHT)}
    for b in bnds[1:]:
        key = min(ends, key=lambda k: np.linalg.norm(np.array(k) - b["centre"]))
        assert np.linalg.norm(np.array(key) - b["centre"]) < 0.05
        assert np.allclose(b["normal"], ends.pop(key), atol=1e-2)  # the merged spine ends within 0.6 deg
        assert b["area_mm2"] == pytest.approx(np.pi * 1.4**2, rel=0.01)
    assert not ends
    assert surf.is_watertight and surf.is_winding_consistent and surf.volume > 0


def _signed_volumes(points, cells):
    """Independent of the quality module: determinant of the edge vectors of each tet / sub-tet."""
    p = points[cells]
    if cells.shape[1] == 4:
        return np.linalg.det(np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], 1)) / 6
    # wedge: the three tets of the standard split
    out = 0
    for a, b, c, d in ((0, 1, 2, 3), (1, 2, 3, 4), (2, 3, 4, 5)):
        out = out + np.linalg.det(np.stack([p[:, b] - p[:, a], p[:, c] - p[:, a], p[:, d] - p[:, a]], 1)) / 6
    return out


def test_volume_mesh_positive_elements_groups_and_files(y_volume, y_solid, tmp_path):
    m = y_volume
    assert set(m.cells) == {"tetra"}
    vols = _signed_volumes(m.points, m.cells["tetra"])
    assert np.all(vols > 0)
    assert vols.sum() == pytest.approx(y_solid.volume, rel=0.02)
    assert m.quality["tetra"]["inverted"] == 0 and m.quality["tetra"]["scaled_jacobian_min"] > 0.1
    assert set(m.groups) == {"fluid", "wall", "inlet", "outlet_1", "outlet_2"}
    # the boundary of the volume mesh is the labelled surface: closed, outward
    surf = m.surface()
    assert surf.is_watertight and surf.volume == pytest.approx(vols.sum(), rel=1e-9)

    for version in (4.1, 2.2):
        path = tmp_path / f"y{version}.msh"
        side = m.write(path, msh_version=version)
        assert path.read_text().startswith(f"$MeshFormat\n{version}")
        back = meshio.read(path)
        assert set(back.field_data) == set(m.groups)
        assert back.field_data["fluid"].tolist() == [1, 3]
        assert sum(len(c.data) for c in back.cells if c.type == "tetra") == len(m.cells["tetra"])
    doc = json.loads(side.read_text())
    assert doc["mesh_file"] == "y2.2.msh"
    assert [o["name"] for o in doc["outlets"]] == ["outlet_1", "outlet_2"]
    assert doc["inlets"][0]["branch"] == "main/left"  # merged with the child it continues into
    assert doc["inlets"][0]["equivalent_radius_mm"] == pytest.approx(2.0, rel=0.01)

    m.write(tmp_path / "y.vtu")
    back = meshio.read(tmp_path / "y.vtu")
    ids = np.concatenate(back.cell_data["CellEntityIds"])
    assert set(np.unique(ids)) == {0, 1, 2, 3, 4}
    m.write(tmp_path / "y.xdmf")
    assert (tmp_path / "y.h5").is_file()
    assert meshio.read(tmp_path / "y.xdmf").points.shape == m.points.shape


def test_boundary_layers_are_prisms_of_the_asked_thickness(tube_solid, y_solid):
    n, first, growth = 3, 0.03, 1.3
    expected = first * growth ** np.arange(n)  # layer thicknesses / radius
    m = vc.cfd.volume_mesh(tube_solid, edge_factor=0.4, boundary_layers=n, first_layer=first, growth=growth)
    assert {"tetra", "wedge"} <= set(m.cells)
    p = m.points - START
    radial = np.linalg.norm(p - np.outer(p @ AXIS, AXIS), axis=1)
    w = m.cells["wedge"]
    # each wedge spans one layer: its bottom and top triangles lie on cylinders of known radii
    levels = R_TUBE * (1 - np.r_[0.0, np.cumsum(expected)])
    bottom, top = radial[w[:, :3]].mean(axis=1), radial[w[:, 3:]].mean(axis=1)
    k = np.argmin(np.abs(bottom[:, None] - levels[None, :-1]), axis=1)
    assert np.allclose(bottom, levels[k], atol=1e-3 * R_TUBE)
    assert np.allclose(top, levels[k + 1], atol=1e-3 * R_TUBE)
    assert set(np.unique(k)) == set(range(n))
    # the tetrahedra fill the core inside the last layer
    core = radial[np.unique(m.cells["tetra"])]
    assert core.max() == pytest.approx(levels[-1], abs=1e-3 * R_TUBE)
    assert m.boundaries[0].area_mm2 == pytest.approx(np.pi * R_TUBE**2, rel=0.01)  # ribbons + inner disc

    # and a bifurcation: no inverted element, the same groups, a closed labelled boundary
    m = vc.cfd.volume_mesh(y_solid, edge_factor=0.4, boundary_layers=n, first_layer=first, growth=growth)
    for kind in ("tetra", "wedge"):
        assert np.all(_signed_volumes(m.points, m.cells[kind]) > 0)
        assert m.quality[kind]["inverted"] == 0
    assert set(m.groups) == {"fluid", "wall", "inlet", "outlet_1", "outlet_2"}
    surf = m.surface()
    assert surf.is_watertight and surf.is_winding_consistent
    assert surf.volume == pytest.approx(y_solid.volume, rel=0.02)


def test_flow_extensions_are_exact_cylinders(tube_solid):
    ext = tube_solid.with_flow_extensions(inlet=2, outlet=3)
    chk = ext.check()
    assert chk["watertight"]
    total = L_TUBE + 2 * 2 * R_TUBE + 3 * 2 * R_TUBE
    assert ext.volume == pytest.approx(np.pi * R_TUBE**2 * total, rel=1e-5)
    caps = ext.caps()
    assert np.allclose(caps[0]["centre"], START - 4 * R_TUBE * AXIS, atol=1e-4)
    assert np.allclose(caps[1]["centre"], START + (L_TUBE + 6 * R_TUBE) * AXIS, atol=1e-4)
    surf = vc.cfd.surface_mesh(tube_solid, flow_extensions=(2, 3))
    b = surf.metadata["boundaries"]
    assert b[1]["extension_mm"] == pytest.approx(6 * R_TUBE)
    assert np.allclose(b[1]["centre"], caps[1]["centre"], atol=1e-4)
    assert b[1]["area_mm2"] == pytest.approx(np.pi * R_TUBE**2, rel=0.01)
    assert surf.volume == pytest.approx(np.pi * R_TUBE**2 * total, rel=0.02)


def test_flow_extension_is_shortened_before_it_runs_into_the_tree():
    # An L: the child's end points at the parent 6 mm away; a 5-diameter extension would hit it.
    tree = _tree([
        {"id": 0, "parent": None, "points": _line([0, 0, 0], [0, 0, 1], 40).tolist(), "radius": [1.5] * 30},
        {"id": 1, "parent": 0, "points": np.vstack([_line([0, 0, 10], [1, 0, 0], 10, 10)[:-1],
                                                    _line([10, 0, 10], [0, 0, 1], 15, 10)[:-1],
                                                    _line([10, 0, 25], [-1, 0, 0], 2.5, 5)]).tolist(),
         "radius": [1.0] * 23},
    ])
    ext = tree.solid().with_flow_extensions(outlet=5)
    assert ext.check()["watertight"]
    assert any("branch 1" in w and ("shortened" in w or "no flow extension" in w) for w in ext.warnings)
    assert ext.extensions.get((1, "outlet"), 0.0) < 10.0


def test_surface_writers(y_solid, tmp_path):
    surf = vc.cfd.surface_mesh(y_solid, edge_factor=0.5)
    mesh = surf.metadata["cfd_mesh"]
    mesh.write(tmp_path / "y.stl")
    text = (tmp_path / "y.stl").read_text()
    assert [line.split()[1] for line in text.splitlines() if line.startswith("solid ")] == \
        ["wall", "inlet", "outlet_1", "outlet_2"]
    assert text.count("facet normal") == len(surf.faces)
    mesh.write(tmp_path / "y_surface.msh", msh_version=2.2)
    back = meshio.read(tmp_path / "y_surface.msh")
    assert set(back.field_data) == {"wall", "inlet", "outlet_1", "outlet_2"}
    with pytest.raises(vc.ArgumentError, match="unknown mesh format"):
        mesh.write(tmp_path / "y.foo")


def test_bad_input_is_named():
    with pytest.raises(vc.ArgumentError, match="edge_factor"):
        vc.cfd.surface_mesh("nowhere", edge_factor=-1)
    with pytest.raises(vc.InputFileError, match="nowhere"):
        vc.cfd.surface_mesh("nowhere")
    with pytest.raises(vc.ArgumentError, match="flow_extensions"):
        vc.cfd.load_solid("nowhere", flow_extensions=(1, 2, 3))
    with pytest.raises(vc.ArgumentError, match="boundary layers"):
        vc.cfd.volume_mesh("nowhere", boundary_layers=20, first_layer=0.1)


def test_quality_measures_on_known_elements():
    tet = np.array([[1, 1, 1], [-1, 1, -1], [1, -1, -1], [-1, -1, 1]], float)  # regular, positive
    assert np.linalg.det(tet[1:] - tet[0]) > 0
    assert scaled_jacobian(tet, [[0, 1, 2, 3]], "tetra")[0] == pytest.approx(1.0)
    assert scaled_jacobian(tet, [[0, 2, 1, 3]], "tetra")[0] == pytest.approx(-1.0)  # inverted
    assert aspect_ratio(tet, [[0, 1, 2, 3]], "tetra")[0] == pytest.approx(1.0)
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.3, 0.3, 1e-9]])
    assert abs(scaled_jacobian(flat, [[0, 1, 2, 3]], "tetra")[0]) < 1e-6
    tri = np.array([[0, 0, 0], [1, 0, 0], [0.5, np.sqrt(3) / 2, 0]])
    wedge = np.vstack([tri, tri + [0, 0, 1]])
    assert scaled_jacobian(wedge, [[0, 1, 2, 3, 4, 5]], "wedge")[0] == pytest.approx(1.0)
    assert aspect_ratio(tri, [[0, 1, 2]], "triangle")[0] == pytest.approx(1.0)
    a = 1.0
    pyr = np.array([[0, 0, 0], [a, 0, 0], [a, a, 0], [0, a, 0], [a / 2, a / 2, a / np.sqrt(2)]])
    assert scaled_jacobian(pyr, [[0, 1, 2, 3, 4]], "pyramid")[0] == pytest.approx(1.0)


def test_radius_field_assigns_points_to_their_vessel():
    z = np.linspace(0, 20, 81)
    main = np.c_[np.zeros_like(z), np.zeros_like(z), z]
    side = np.c_[np.linspace(0, 10, 41), np.zeros(41), np.full(41, 10.0)]
    field = RadiusField(np.vstack([main, side]), np.r_[np.full(81, 3.0), np.full(41, 0.5)])
    # on the big wall next to the small branch's axis: the big vessel's radius
    assert field(np.array([[-2.9, 0.0, 10.4]]))[0] == 3.0
    assert field(np.array([[8.0, 0.4, 10.0]]))[0] == 0.5
    cb = field.size_callback(0.3, 0.01, 10.0)
    assert cb(2, 1, 0.0, 2.0, 5.0, 1e22) == pytest.approx(0.9, rel=1e-6)
    assert cb(2, 1, 8.0, 0.4, 10.0, 1e22) == pytest.approx(0.15, rel=1e-6)


def test_size_near_short_edges_grades_from_the_nearest_point_and_its_least_size():
    # One vessel of radius 1 along z (size 0.3 there); three points that need small elements,
    # the first listed twice (one size per close partner): its least size counts.
    z = np.linspace(0, 20, 81)
    field = RadiusField(np.c_[np.zeros_like(z), np.zeros_like(z), z], np.ones(81))
    pts = np.array([[1.0, 0.0, 5.0], [1.0, 0.0, 5.0], [0.0, 1.0, 9.0], [-1.0, 0.0, 9.3]])
    sizes = np.array([0.05, 0.01, 0.02, 0.04])
    grading = 0.3
    cb = field.size_callback(0.3, 0.001, 10.0, refine=(pts, sizes), grading=grading)
    assert cb(2, 1, 1.0, 0.0, 5.0, 1e22) == pytest.approx(0.01, rel=1e-6)
    assert cb(2, 1, 0.0, 1.0, 9.0, 1e22) == pytest.approx(0.02, rel=1e-6)
    assert cb(2, 1, -1.0, 0.0, 9.3, 1e22) == pytest.approx(0.04, rel=1e-6)
    # Within 0.27 mm of them (voxels of 0.25 mm whose centre lies within 2 voxels of a point, where
    # the callback looks the point up): no larger than the size graded from the nearest point (brute
    # force), and no smaller than the least graded size minus what the tabulation allows.
    uniq, least = pts[1:], sizes[1:]
    rng = np.random.default_rng(0)
    off = rng.normal(0.0, 1.0, (400, 3))
    off *= rng.uniform(0.0, 0.27, (400, 1)) / np.linalg.norm(off, axis=1, keepdims=True)
    q = uniq[rng.integers(0, 3, 400)] + off
    got = np.array([cb(2, 1, *p, 1e22) for p in q])
    d = np.linalg.norm(q[:, None] - uniq[None], axis=-1)
    nearest = least[np.argmin(d, axis=1)] + grading * d.min(axis=1)
    assert np.all(got <= np.minimum(nearest, 0.3) * (1 + 1e-6))  # the table holds float32
    assert np.all(got >= (least[None] + grading * d).min(axis=1) - grading * 0.25 * np.sqrt(3) / 2)


def test_cli_mesh(y_tree, tmp_path, capsys):
    case = tmp_path / "case"
    case.mkdir()
    y_tree.to_json(case / "centrelines.json")
    out = tmp_path / "mesh" / "y.vtu"
    rc = main(["mesh", str(case), "--out", str(out), "--edge-factor", "0.5", "--flow-extensions", "1",
               "--png", str(tmp_path / "y.png"), "--quiet", "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert out.is_file() and (tmp_path / "y.png").is_file()
    assert [b["name"] for b in summary["boundaries"]] == ["inlet", "outlet_1", "outlet_2"]
    assert summary["elements"]["tetra"] > 0
    doc = json.loads((tmp_path / "mesh" / "y.bc.json").read_text())
    assert doc["outlets"][0]["extension_mm"] == pytest.approx(2 * 1.4, rel=1e-3)
    assert main(["mesh", str(tmp_path / "none"), "--out", str(out)]) == 2


def test_inverted_sites_name_where_and_which_branches(y_volume):
    from dataclasses import replace

    assert vc.cfd.inverted_sites(y_volume) == []
    # Invert (swap two nodes of) the tetrahedron nearest a point inside the main vessel's wall
    # far from the junction, and the one nearest a point inside the right child's wall.
    tets = y_volume.cells["tetra"].copy()
    centroids = y_volume.points[tets].mean(axis=1)
    targets = {0: np.array([1.8, 0.0, 5.0]), 2: JOIN + 18.0 * RIGHT + np.array([0.0, 1.25, 0.0])}
    picked = {b: int(np.argmin(np.linalg.norm(centroids - q, axis=1))) for b, q in targets.items()}
    for k in picked.values():
        tets[k, [0, 1]] = tets[k, [1, 0]]
    sites = vc.cfd.inverted_sites(replace(y_volume, cells={"tetra": tets}))
    assert len(sites) == 2
    for centre, count, branches in sites:
        b = min(picked, key=lambda b: np.linalg.norm(centroids[picked[b]] - centre))
        np.testing.assert_allclose(centre, centroids[picked[b]], atol=1e-9)
        assert count == 1 and branches == [b]
    with pytest.raises(vc.VesselcadError, match="radius_mm"):
        vc.cfd.inverted_sites(y_volume, radius_mm=0)
    with pytest.raises(vc.VesselcadError, match="CFDMesh"):
        vc.cfd.inverted_sites("mesh.msh")
    with pytest.raises(vc.VesselcadError, match="threshold"):
        vc.cfd.inverted_sites(y_volume, threshold=2.0)
    # threshold 1: every element counts, and the Y's elements form one connected site
    (_c, count, _branches), = vc.cfd.inverted_sites(y_volume, radius_mm=1.0, threshold=1.0)
    assert count == len(y_volume.cells["tetra"])


def test_edges_passing_close_without_meeting_refine_the_size():
    # Two straight B-rep edges, one along x through the origin, one along z through
    # (5, 0.02, 0): they pass 0.02 mm apart at x = 5, 5 mm from any vertex. The sizes
    # asked there are that gap (to the sampling's 0.04 mm); edges meeting at a vertex
    # at 90 degrees ask nothing.
    import gmsh

    from vesselcad.cfd.mesher import _short_curves

    field = RadiusField(np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]), np.array([2.0, 2.0]))
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        occ = gmsh.model.occ
        occ.addLine(occ.addPoint(0, 0, 0), occ.addPoint(10, 0, 0))
        occ.addLine(occ.addPoint(5, 0.02, -5), occ.addPoint(5, 0.02, 5))
        occ.addLine(occ.addPoint(0, 20, 0), occ.addPoint(10, 20, 0))  # two edges meeting
        occ.addLine(occ.addPoint(10, 20, 0), occ.addPoint(10, 30, 0))  # at a right angle
        occ.synchronize()
        pts, size = _short_curves(gmsh, field, edge_factor=0.3, min_size=0.1)
    finally:
        gmsh.finalize()
    assert len(pts) > 0
    # within half the element size (0.3 mm) of the closest approach, none at the corner
    assert np.all(np.linalg.norm(pts - [5.0, 0.01, 0.0], axis=1) <= 0.3 + 0.03)
    assert size.min() == pytest.approx(0.02, abs=1e-6)
    # each point asks for the distance between the two edges' samples there (>= its own
    # distance to the other edge, < 0.3 mm)
    to_other = np.where(pts[:, 1] > 0.01, np.hypot(pts[:, 1], pts[:, 2]), np.hypot(pts[:, 0] - 5.0,
                                                                                pts[:, 1] - 0.02))
    assert np.all(size >= to_other - 1e-9) and np.all(size < 0.3)


def test_touching_vessels_are_moved_apart_before_meshing():
    # Two daughters whose axes cross (tests/test_solids.py): meshed from the tree they are
    # moved apart first (named in the warnings), so the fluid does not join them there and
    # the prism layers do not fold; the surface then has no handle (Euler characteristic 2).
    up, down = np.array([1.0, 0.0, 1.0]) / np.sqrt(2), np.array([1.0, 0.0, -1.0]) / np.sqrt(2)
    tree = _tree([
        {"id": 0, "parent": None, "name": "root", "points": _line([0, 0, 0], [0, 0, 1], 40).tolist(),
         "radius": [2.0] * 30},
        {"id": 1, "parent": 0, "name": "up", "points": _line([0, 0, 5], up, 25).tolist(),
         "radius": [1.0] * 30},
        {"id": 2, "parent": 0, "name": "down", "points": _line([0, 0, 25], down, 25).tolist(),
         "radius": [1.0] * 30},
    ])
    surf = vc.cfd.surface_mesh(tree, edge_factor=0.5)
    mesh = surf.metadata["cfd_mesh"]
    assert any("branch 1 (up)" in w and "moved up to 1.1" in w for w in mesh.warnings)
    assert not any("touch away" in w for w in mesh.warnings)
    assert surf.is_watertight and surf.euler_number == 2
    kept = vc.cfd.load_solid(tree, separate_contacts=False)
    assert any("touch away from a junction" in w for w in kept.warnings)


def test_crossing_triangles_finds_only_triangles_that_pass_through_each_other():
    from vesselcad.cfd.quality import crossing_triangles

    pts = np.array([
        [0, 0, 0], [2, 0, 0], [0, 2, 0],          # 0: flat triangle in z = 0
        [0.5, 0.5, -1], [0.6, 0.5, 1], [0.5, 0.6, 1],  # 1: its edge 3-4 pierces triangle 0 at (0.55, 0.5, 0)
        [5, 5, 5], [6, 5, 5], [5, 6, 5],          # 2: far away
        [2, 0, 0], [2, 2, 1], [3, 0, 1],          # 3: touches triangle 0 at a corner only (equal point)
    ], float)
    tris = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8], [1, 10, 11]])
    i, j = crossing_triangles(pts, tris)
    assert list(zip(i.tolist(), j.tolist(), strict=True)) == [(0, 1)]
    # a closed octahedron does not cross itself, nor does a tetrahedron's surface
    octa = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    assert len(crossing_triangles(octa, faces)[0]) == 0
    # with a copy of itself shifted by half its size, each surface passes through the other
    both = np.vstack([octa, octa + [0.5, 0.3, 0.1]])
    i, j = crossing_triangles(both, np.vstack([faces, faces + 6]))
    assert len(i) > 0 and np.all(i < 8) and np.all(j >= 8)
    with pytest.raises(vc.ArgumentError, match="triangles"):
        crossing_triangles(octa, np.array([[0, 1, 9]]))


def _fork_at_end(angle_deg=70.0, r_child=1.2):
    """Parent r = 1.5 along z to 20 mm; two children start at its very end at +-angle (skeleton style)."""
    a = np.radians(angle_deg)
    join = np.array([0.0, 0.0, 20.0])
    return _tree([
        {"id": 0, "parent": None, "points": _line([0, 0, 0], [0, 0, 1], 20).tolist(), "radius": [1.5] * 30},
        {"id": 1, "parent": 0, "points": _line(join, [np.sin(a), 0, np.cos(a)], 15).tolist(),
         "radius": [r_child] * 30},
        {"id": 2, "parent": 0, "points": _line(join, [-np.sin(a), 0, np.cos(a)], 15).tolist(),
         "radius": [r_child] * 30},
    ])


def test_prism_layers_at_a_fork_at_a_vessel_end():
    # Skeleton graphs end a parent where its children start. Closed with a disc, that end
    # left slivers against the children's walls where three prism layers crossed or folded
    # (real-shaped trees: gmsh stopped with "a segment and a facet intersect"); the dome
    # that closes it now meshes with no inverted element and a scaled Jacobian above 0.1.
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        m = vc.cfd.volume_mesh(_fork_at_end(), boundary_layers=3)
    assert not [w for w in caught if "prism layers" in str(w.message) or "inverted" in str(w.message)]
    for kind in ("wedge", "tetra"):
        assert m.quality[kind]["inverted"] == 0
        assert m.quality[kind]["scaled_jacobian_min"] > 0.1
    assert [b.role for b in m.boundaries] == ["inlet", "outlet", "outlet"]


def test_prism_layers_that_would_cross_are_thinned_there():
    # The same fork closed with a flat disc (as before the domes): the layers' top surface
    # would cross itself at the junction, which gmsh's tetrahedra cannot fill. The mesher
    # finds the crossing triangles, thins the layers around them and meshes again, and
    # says where it did so.
    import re

    from vesselcad.kernel.pipes import branch_pipe
    from vesselcad.kernel.solid import fuse_pipes

    specs = _fork_at_end().pipe_specs()
    assert [s["end"] for s in specs] == ["dome", "flat", "flat"]
    solid = fuse_pipes([branch_pipe(s["id"], s["name"], s["parent"], s["spine"], s["radius"])
                        for s in specs])  # every end flat
    solid.specs = specs
    with pytest.warns(vc.VesselcadWarning, match="prism layers would cross"):
        m = vc.cfd.volume_mesh(solid, boundary_layers=3)
    note = next(w for w in m.warnings if "prism layers would cross" in w)
    sites = np.array(re.findall(r"\(([-\d.]+), ([-\d.]+), ([-\d.]+)\) mm", note), float)
    assert len(sites) and np.all(np.linalg.norm(sites - [0, 0, 20], axis=1) < 3.0)  # at the fork
    assert m.quality["tetra"]["inverted"] == 0
