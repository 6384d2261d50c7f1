"""CAD mode: snap boundary vertices onto the faces and edges of a CAD model.

See :class:`CadGeometry`.
"""

from .geometry import CadError, CadGeometry, TrimLoops

__all__ = ["CadError", "CadGeometry", "TrimLoops"]
