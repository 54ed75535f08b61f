"""The pinned CAD stack: build123d and cadquery must share ONE OCP (OCCT) in one environment."""

import sys


def test_build123d_and_cadquery_share_one_ocp():
    import build123d
    import cadquery as cq
    import OCP

    box_b = build123d.Box(1, 2, 3)
    box_c = cq.Workplane().box(1, 2, 3).val()
    assert abs(box_b.volume - 6.0) < 1e-9 and abs(box_c.Volume() - 6.0) < 1e-9
    # One OCP: a build123d shape is usable by cadquery and back, and both are OCP.TopoDS shapes.
    from OCP.TopoDS import TopoDS_Shape

    assert isinstance(box_b.wrapped, TopoDS_Shape) and isinstance(box_c.wrapped, TopoDS_Shape)
    solid_b = box_b.solids()[0]
    as_cq = cq.Shape.cast(solid_b.wrapped)
    assert abs(as_cq.Volume() - 6.0) < 1e-9
    back = build123d.Solid(box_c.wrapped)
    assert abs(back.volume - 6.0) < 1e-9
    assert len({sys.modules[m].__file__ for m in sys.modules if m == "OCP"}) == 1 and OCP.__file__


def test_public_api_names():
    import vesselcad as vc

    for name in ("CArmView", "XARun", "load_run", "save_run", "triangulate", "reconstruction_error",
                 "VesselcadError", "MissingGeometryError", "DicomError", "DecoderError"):
        assert hasattr(vc, name), name
    assert issubclass(vc.MissingGeometryError, vc.VesselcadError)
    assert issubclass(vc.GeometryError, ValueError)
