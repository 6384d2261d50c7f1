"""The error of CAD mode, for the modules of ``nagata_snap.cad`` (defined in :mod:`nagata_snap.errors`)."""

from nagata_snap.errors import CadError

__all__ = ["CadError"]
