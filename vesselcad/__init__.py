"""vesselcad: 3D coronary vessel trees from two X-ray angiography runs, as CAD geometry.

The public API is re-exported here; see docs/ for the geometry convention,
file formats and the command line.
"""

from __future__ import annotations

from .batch import BatchCase, BatchResult, find_cases, run_batch
from .centreline2d import Branch2D, CentrelineGraph, Crossing, Landmark, centreline_graph
from .centreline3d import intersect_centrelines
from .errors import (
    ArgumentError,
    DecoderError,
    DicomError,
    GeometryError,
    InputFileError,
    MeshError,
    MissingGeometryError,
    OutputError,
    VesselcadError,
    VesselcadWarning,
)
from .geometry import CArmView, Reconstruction2View, reconstruction_error, triangulate
from .io import XARun, load_run, save_run
from .matching import BranchPair, GraphMatch, LandmarkMatch, Unmatched, match_graphs, plot_graph_match
from .metrics import MaskReprojection, centreline_error, mask_reprojection, reprojection_error
from .phase import PhaseError, PhaseMatch, match_phase
from .pipeline import BranchResult, Reconstruction, ReconstructionError, reconstruct
from .refine import Refinement, keypoint_shift, landmark_shift, refine_geometry
from .segment import Segmenter
from .tree import TreeBranch, VesselTree

__version__ = "0.1.0"


def __getattr__(name: str):
    # The solid class lives behind the OCCT door; import it only when asked for.
    if name == "VesselSolid":
        from .kernel.solid import VesselSolid

        return VesselSolid
    if name == "cfd":  # gmsh and meshio load only for meshing
        import importlib

        return importlib.import_module(".cfd", __name__)
    raise AttributeError(f"module 'vesselcad' has no attribute {name!r}")

__all__ = [
    "run_batch",
    "find_cases",
    "BatchCase",
    "BatchResult",
    "CArmView",
    "Reconstruction2View",
    "XARun",
    "load_run",
    "save_run",
    "Segmenter",
    "match_phase",
    "PhaseMatch",
    "PhaseError",
    "triangulate",
    "intersect_centrelines",
    "centreline_graph",
    "CentrelineGraph",
    "Landmark",
    "Branch2D",
    "Crossing",
    "match_graphs",
    "GraphMatch",
    "BranchPair",
    "LandmarkMatch",
    "Unmatched",
    "plot_graph_match",
    "VesselTree",
    "TreeBranch",
    "reconstruct",
    "Reconstruction",
    "ReconstructionError",
    "BranchResult",
    "refine_geometry",
    "keypoint_shift",
    "landmark_shift",
    "Refinement",
    "VesselSolid",
    "cfd",
    "reprojection_error",
    "centreline_error",
    "mask_reprojection",
    "MaskReprojection",
    "reconstruction_error",
    "VesselcadError",
    "ArgumentError",
    "GeometryError",
    "InputFileError",
    "DicomError",
    "MissingGeometryError",
    "DecoderError",
    "OutputError",
    "MeshError",
    "VesselcadWarning",
    "__version__",
]
