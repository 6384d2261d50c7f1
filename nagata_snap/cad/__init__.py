"""CAD mode: snap boundary vertices onto the faces, edges and vertices of a CAD model.

Modules:

* :mod:`~nagata_snap.cad.read`: OpenCASCADE (OCP) reads STEP, IGES and BREP
  files into plain data (the only module that calls OpenCASCADE);
  :mod:`~nagata_snap.cad.sewing` sews faces-only files on that data;
  :mod:`~nagata_snap.cad.worker` runs it in a child process;
* :mod:`~nagata_snap.cad.topology`: the B-rep as faces, edges, vertices and
  trimming loops (:class:`~nagata_snap.cad.topology.CadModel`);
* :mod:`~nagata_snap.cad.surfaces`, :mod:`~nagata_snap.cad.curves`: analytic
  faces and edges with closed-form projection; :mod:`~nagata_snap.cad.nurbs`
  the rest;
* :mod:`~nagata_snap.cad.projection`: Newton projection, search grids;
* :mod:`~nagata_snap.cad.trimming`: point-in-face;
* :mod:`~nagata_snap.cad.geometry`: :class:`CadGeometry`, the snapping
  geometry, whose stages are :mod:`~nagata_snap.cad.attach` (coarse facets
  onto their faces), :mod:`~nagata_snap.cad.place` (snapping after a
  refinement) and :mod:`~nagata_snap.cad.features` (CAD edges and corners),
  over :mod:`~nagata_snap.cad.params` (seams, poles, normals) and
  :mod:`~nagata_snap.cad.slots`;
* :mod:`~nagata_snap.cad.meshed`: a gmsh mesh of the file and its geometry,
  matched (:func:`mesh_cad`);
* :mod:`~nagata_snap.cad.iges`: an IGES writer (tests).
"""

from nagata_snap.cad.geometry import CadError, CadGeometry
from nagata_snap.cad.meshed import mesh_cad
from nagata_snap.cad.trimming import TrimLoops

__all__ = ["CadError", "CadGeometry", "TrimLoops", "mesh_cad"]
