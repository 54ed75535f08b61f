"""Exceptions and warnings raised by vesselcad.

Every public function rejects bad input with a subclass of
:class:`VesselcadError` whose message names the file, the DICOM tag or the
argument at fault and says what was expected. The subclasses also derive from
the matching built-in exception (``ValueError``, ``FileNotFoundError``) so
code written against the standard library keeps working.
"""

from __future__ import annotations

__all__ = [
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
]


class VesselcadError(Exception):
    """Base class of every error vesselcad raises on purpose."""


class ArgumentError(VesselcadError, ValueError):
    """A function argument has the wrong type, shape or value."""


class GeometryError(ArgumentError):
    """A C-arm geometry is impossible (e.g. SOD >= SID, zero pixel spacing)."""


class InputFileError(VesselcadError, OSError):
    """An input file or folder is missing, unreadable or of the wrong kind."""


class DicomError(InputFileError):
    """A DICOM file is not a usable X-ray angiography run."""


class MissingGeometryError(DicomError):
    """A DICOM file lacks the tags that define its projection geometry.

    Attributes
    ----------
    missing : list of str
        The ``CArmView`` keyword names that could not be found.
    """

    def __init__(self, message: str, missing: list[str]):
        super().__init__(message)
        self.missing = list(missing)


class DecoderError(DicomError):
    """No installed pixel decoder can decode the file's transfer syntax."""


class OutputError(VesselcadError, OSError):
    """An output file or folder cannot be created or written."""


class MeshError(VesselcadError, RuntimeError):
    """The mesher (gmsh) could not mesh a solid; the message names the stage and the surface."""


class VesselcadWarning(UserWarning):
    """Something was guessed or fell back to a default; the message says what."""
