"""The error of CAD mode (a module of its own so that every stage can raise it)."""

from __future__ import annotations

__all__ = ["CadError"]


class CadError(RuntimeError):
    """The mesh boundary does not match the CAD geometry, or the CAD file cannot be used."""
