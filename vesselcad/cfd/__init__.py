"""CFD meshes of vessel trees: labelled surfaces, flow extensions, volume meshes with boundary layers.

>>> import vesselcad as vc
>>> surf = vc.cfd.surface_mesh("case/centrelines.json", flow_extensions=5)   # trimesh.Trimesh
>>> mesh = vc.cfd.volume_mesh("case/", boundary_layers=4, flow_extensions=(3, 5))
>>> mesh.write("tree.msh", msh_version=2.2)        # + tree.bc.json (inlet/outlets for the solver)

Groups (gmsh physical groups, ``CellEntityIds`` in VTK files, STL solid
names): ``fluid`` (0; physical volume 1 in .msh), ``wall`` (1), ``inlet``
(2), ``outlet_1``, ``outlet_2``, ... (3, 4, ...). See docs/cfd.md.
"""

from .mesher import (
    FLUID_ID,
    INLET_ID,
    WALL_ID,
    Boundary,
    CFDMesh,
    inverted_sites,
    load_solid,
    surface_mesh,
    volume_mesh,
)
from .quality import aspect_ratio, quality_report, scaled_jacobian
from .sizing import RadiusField

__all__ = ["surface_mesh", "volume_mesh", "load_solid", "inverted_sites", "CFDMesh", "Boundary",
           "RadiusField", "scaled_jacobian", "aspect_ratio", "quality_report", "FLUID_ID", "WALL_ID",
           "INLET_ID"]
