"""Biplane angiography phantom: moving vessel trees, devices, X-ray physics, ground truth.

The phantom is the measuring stick of every later stage (see docs/phantom.md).
"""

from __future__ import annotations

from .anatomy import ANATOMIES
from .case import LABELS, PhantomCase, RenderedRun, default_views, generate_case, render, write_case

__all__ = [
    "ANATOMIES",
    "LABELS",
    "PhantomCase",
    "RenderedRun",
    "default_views",
    "generate_case",
    "render",
    "write_case",
]
