"""Nagata-mode geometry: curved patches over the coarse boundary, no CAD needed.

:class:`NagataGeometry` is built once from the coarse mesh and its facet tags.
It gathers the whole coarse boundary on every process in a canonical order
(facets sorted by the input-global indices of their vertices), so patch data
and therefore snapped coordinates are identical whatever the partition.

It is a :class:`~nagata_snap.geometry.SnapGeometry`: ``attach`` gives each
coarse facet its own patch as record (barycentric coordinates of its
vertices), ``place`` evaluates a facet vertex on the patch of its record,
``project`` finds closest points on a facet's own patch (for boundary
vertices that slide during the repair, :mod:`nagata_snap.smoothing.slide`).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence

import dolfinx.mesh
import numpy as np
import numpy.typing as npt
from mpi4py import MPI
from scipy.spatial import cKDTree

from nagata_snap.geometry import PlaceReport
from nagata_snap.mesh.boundary import (
    boundary_facets,
    check_snap_input,
    facet_normal_vectors,
    tag_values,
)
from nagata_snap.mesh.parallel import collective
from nagata_snap.mesh.records import Records
from nagata_snap.nagata import patch as patches
from nagata_snap.nagata.normals import NormalsError, corner_normals

__all__ = ["NagataGeometry", "NormalSource"]

#: Vertex normals: ``None`` or a name from :data:`nagata_snap.nagata.normals.SCHEMES`
#: (estimate; ``None`` is ``"jet"``), an array ``(num_nodes, gdim)`` over the
#: coarse mesh's local geometry nodes, a callable ``f(x) -> n`` mapping
#: ``(k, 3)`` points to ``(k, 3)`` (or ``(k, gdim)``) normals, or a CAD
#: geometry: any object with ``attach(facet_points, nodes) -> records`` and
#: ``vertex_normals(records) -> (nf, nfv, 3)`` (e.g. ``CadGeometry``), whose
#: normals are taken per facet on the facet's own CAD face.
NormalSource = None | str | np.ndarray | Callable[[np.ndarray], np.ndarray] | object

#: Corners of one smooth sector whose supplied normals (CAD faces meeting
#: tangentially) differ by at most this many degrees share their mean.
SECTOR_MERGE_DEG = 1.0


def _is_cad(normals) -> bool:
    return hasattr(normals, "attach") and hasattr(normals, "vertex_normals")


def _unit(n: np.ndarray, what: str, at: np.ndarray | None = None) -> np.ndarray:
    """Unit vectors of ``n (..., 3)``; ``NormalsError`` for zero/NaN ones (``at``: their points)."""
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    bad = ~(np.isfinite(n).all(axis=-1) & (norm[..., 0] > 1e-12))
    if bad.any():
        where = f"; first at {np.round(at[bad][0], 6).tolist()}" if at is not None else ""
        raise NormalsError(f"{int(bad.sum())} {what} normals are zero, NaN or infinite{where}")
    return n / norm


def _check_facet_area(fnorm: np.ndarray, coords: np.ndarray) -> None:
    """``NormalsError`` naming zero-area boundary facets (their normal is undefined).

    ``fnorm (F, 3)`` are the facet normals (unit or not, NaN for degenerate
    facets), ``coords (F, nfv, 3)`` the facet vertices.
    """
    norm = np.linalg.norm(fnorm, axis=1)
    bad = ~(np.isfinite(norm) & (norm > 1e-12))
    if bad.any():
        raise NormalsError(
            f"{int(bad.sum())} boundary facets have zero area (degenerate facet: its normal "
            f"is undefined); first with vertices {np.round(coords[bad][0], 6).tolist()}"
        )


def _check_coincident(gids: np.ndarray, coords: np.ndarray, snap: np.ndarray) -> None:
    """``ValueError`` if distinct vertices of snapped facets have the same coordinates.

    Duplicate nodes (an unmerged mesh or surface, or a slit whose two sides
    meet a snapped boundary) split the snapped surface into sides that are
    snapped independently, so it would open up or overlap after refinement.
    """
    ids, first = np.unique(gids[snap].ravel(), return_index=True)
    if len(ids) < 2:
        return
    pts = coords[snap].reshape(-1, 3)[first]
    size = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    pairs = cKDTree(pts).query_pairs(1e-12 * size, output_type="ndarray")
    if len(pairs):
        raise ValueError(
            f"{len(pairs)} pairs of distinct vertices of snapped boundary facets have the same "
            f"coordinates (coincident vertices: duplicate nodes, e.g. an unmerged mesh or "
            f"surface); first at {np.round(pts[pairs[0, 0]], 6).tolist()} (vertex ids "
            f"{ids[pairs[0]].tolist()}); merge duplicate nodes before snapping"
        )


def _check_winding(fac: np.ndarray) -> None:
    """``ValueError`` if neighbouring facets of a surface are not consistently oriented.

    A manifold ridge (2D: vertex, 3D: edge) shared by two facets must be
    traversed in opposite directions by them; non-manifold ridges are left to
    :class:`~nagata_snap.nagata.normals.NonManifoldError`.
    """
    nfv = fac.shape[1]
    if nfv == 2:  # each vertex must start one segment and end one
        starts = np.bincount(fac[:, 0], minlength=int(fac.max()) + 1)
        used = np.bincount(fac.ravel(), minlength=len(starts)) == 2
        bad = np.flatnonzero(used & (starts != 1))
        what = "vertices start or end both of their segments"
    else:  # each manifold edge must appear once in each direction
        directed = fac[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        _, inv_u, cnt_u = np.unique(np.sort(directed, axis=1), axis=0, return_inverse=True,
                                    return_counts=True)
        _, inv_d, cnt_d = np.unique(directed, axis=0, return_inverse=True, return_counts=True)
        bad = np.flatnonzero((cnt_u[inv_u.ravel()] == 2) & (cnt_d[inv_d.ravel()] == 2))
        bad = np.unique(np.sort(directed[bad], axis=1), axis=0)
        what = "edges are traversed in the same direction by both of their triangles"
    if len(bad):
        raise ValueError(
            f"facets are not consistently oriented: {len(bad)} {what} (first "
            f"{np.asarray(bad[0]).tolist()}); orient segments counter-clockwise / triangles "
            "with outward winding"
        )


def _gather(comm: MPI.Comm, *arrays: np.ndarray) -> list[np.ndarray]:
    if comm.size == 1:
        return list(arrays)
    parts = comm.allgather(arrays)
    return [np.concatenate([p[i] for p in parts]) for i in range(len(arrays))]


class NagataGeometry:
    """Nagata patches over the tagged boundary facets of a coarse mesh.

    Args:
        mesh: coarse affine triangle (2D) or tetrahedron (3D) mesh.
        facet_tags: its facet tags.
        tags: tag values whose facets are snapped (default: all tags present).
        normals: vertex normals of the snapped surface: ``None`` to estimate
            them (a fourth-order fit of the surface around each vertex, see
            :mod:`nagata_snap.nagata.jets`), the name of an estimate
            (:data:`nagata_snap.nagata.normals.SCHEMES`: ``"jet"`` or one of Neto's
            weighted means such as ``"mwselr"``), an array
            ``(num_geometry_nodes, gdim)`` on the coarse mesh's local geometry
            nodes, a callable of position ``f(x: (k, 3)) -> (k, 3)`` such as an
            analytic normal, or a CAD geometry (an object with ``attach`` and
            ``vertex_normals``, e.g. ``CadGeometry``): each snapped facet's
            corners get the normal of the facet's own CAD face, one per sector.
            Corners where an array's or callable's normal differs from the
            estimated one by more than ``crease_angle`` (the other side of a
            crease) keep the estimated normal.
        crease_angle: degrees; a boundary ridge turning by more than this is
            sharp, and one turning by more than a third of it is sharp when it
            turns more than three times the largest facet-to-facet turn next to
            it on either side (:mod:`nagata_snap.nagata.normals`).  A vertex on a sharp ridge keeps one
            normal per smooth side and the ridge uses the multi-normal
            coefficient (eqs. 20-32 of Nagata 2005).
        split_tags: also treat ridges between facets of different tags as sharp.
        eps: threshold of Nagata's singular-case rules.

    Raises:
        ValueError: unsupported mesh (not affine triangles/tetrahedra, NaN or
            infinite coordinates), unknown tags, tags on interior facets,
            facet tags of another mesh or dimension, coincident vertices on
            snapped facets, malformed ``normals``.
        NormalsError: zero/NaN normals, zero-area facets, or normals more
            than ~155 degrees apart on one edge.
        NonManifoldError: a boundary ridge shared by other than two facets.
    """

    #: keep the jets' facet rings in ``corners.rings`` (a subclass fitting on the same stencils)
    _KEEP_RINGS = False

    def __init__(
        self,
        mesh: dolfinx.mesh.Mesh,
        facet_tags: dolfinx.mesh.MeshTags,
        tags: Sequence[int] | None = None,
        *,
        normals: NormalSource = None,
        crease_angle: float = 60.0,
        split_tags: bool = True,
        eps: float = patches.EPS,
    ):
        self.tags = check_snap_input(mesh, facet_tags, tags)
        comm = mesh.comm
        self.comm = comm
        self.tdim = mesh.topology.dim
        self.gdim = mesh.geometry.dim
        self.crease_angle = float(crease_angle)
        bf = boundary_facets(mesh)
        x = mesh.geometry.x
        gids = np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)[bf.nodes]
        coords = x[bf.nodes]
        tag = tag_values(facet_tags, bf.facet_indices(mesh))
        fnorm = bf.outward_normals(x)
        user = None
        if normals is not None and not callable(normals) and not isinstance(normals, str) \
                and not _is_cad(normals):
            arr = np.asarray(normals, dtype=float)
            bad_shape = arr.ndim != 2 or arr.shape[0] < x.shape[0] or arr.shape[1] not in (2, 3)
            if comm.allreduce(bool(bad_shape), op=MPI.LOR):  # the same error on every process
                raise ValueError(
                    f"normals array must have shape (num_geometry_nodes={x.shape[0]}, gdim), "
                    f"got {arr.shape}" if bad_shape else
                    "normals array has a wrong shape on another process (expected "
                    "(num_geometry_nodes, gdim) there)"
                )
            user = np.zeros((x.shape[0], 3))
            user[:, : arr.shape[1]] = arr[: x.shape[0]]
            user = user[bf.nodes]
        else:
            user = np.zeros_like(coords)
        if _is_cad(normals):  # each process attaches its own facets to their CAD faces
            user = collective(comm, _cad_vertex_normals, normals, coords, gids, np.isin(tag, self.tags))
        gids, coords, tag, fnorm, user = _gather(comm, gids, coords, tag, fnorm, user)
        # every process builds the same patches from the gathered data (no MPI
        # inside); a callable of normals may still fail on some processes only
        collective(comm, self._build, gids, coords, tag, fnorm, user, normals, crease_angle,
                   split_tags, eps)

    @classmethod
    def from_surface(
        cls,
        points: npt.ArrayLike,
        facets: npt.ArrayLike,
        facet_tags: npt.ArrayLike | None = None,
        tags: Sequence[int] | None = None,
        *,
        normals: NormalSource = None,
        crease_angle: float = 60.0,
        split_tags: bool = True,
        eps: float = patches.EPS,
    ) -> NagataGeometry:
        """Nagata patches over a closed polygon (2D) or closed triangulated surface (3D).

        For use without a DOLFINx mesh (tests, benchmarks, surface studies).

        Args:
            points: ``(nv, 3)`` vertex coordinates (or ``(nv, 2)`` for polygons).
            facets: ``(F, 2)`` segments or ``(F, 3)`` triangles, consistently
                oriented (counter-clockwise polygon / outward winding).
            facet_tags: ``(F,)`` tag per facet (default all 0).
            tags: tags whose patches are flagged as snapped (default all).
            normals: as for the constructor; an array is ``(nv, 3)`` per vertex.

        Raises:
            ValueError: malformed arrays (shapes, indices out of range, NaN or
                infinite points), inconsistently oriented facets, coincident
                vertices.
            NormalsError, NonManifoldError: as for the constructor (an open
                polygon/surface is a :class:`NonManifoldError`).
        """
        pts_in = np.asarray(points, dtype=float)
        if pts_in.ndim != 2 or pts_in.shape[1] not in (2, 3):
            raise ValueError(f"points must have shape (nv, 2) or (nv, 3), got {pts_in.shape}")
        fac_in = np.asarray(facets)
        if fac_in.ndim != 2 or fac_in.shape[1] not in (2, 3) or len(fac_in) == 0:
            raise ValueError(
                f"facets must have shape (F, 2) (segments) or (F, 3) (triangles), F >= 1, "
                f"got {fac_in.shape}"
            )
        fac = fac_in.astype(np.int64)
        if not np.array_equal(fac, fac_in):
            raise ValueError("facets must hold integer vertex indices")
        out = (fac < 0) | (fac >= len(pts_in))
        if out.any():
            raise ValueError(
                f"{int(out.sum())} facet vertex indices are outside 0..{len(pts_in) - 1}; "
                f"first {int(fac[out][0])}"
            )
        if not np.all(np.isfinite(pts_in)):
            bad = np.flatnonzero(~np.isfinite(pts_in).all(axis=1))
            raise ValueError(f"{len(bad)} points have NaN or infinite coordinates; first: point {bad[0]}")
        pts = np.zeros((len(pts_in), 3))
        pts[:, : pts_in.shape[1]] = pts_in
        tag = np.zeros(len(fac), dtype=np.int64) if facet_tags is None else np.asarray(facet_tags)
        if tag.shape != (len(fac),):
            raise ValueError(f"facet_tags must have shape ({len(fac)},), got {tag.shape}")
        _check_winding(fac)
        x = pts[fac]
        fn = facet_normal_vectors(x)
        _check_facet_area(fn, x)
        fn = fn / np.linalg.norm(fn, axis=1, keepdims=True)
        self = cls.__new__(cls)
        self.comm = MPI.COMM_SELF
        self.tdim = self.gdim = fac.shape[1]
        self.tags = sorted(set(tag.tolist())) if tags is None else [int(t) for t in tags]
        self.crease_angle = float(crease_angle)
        user = np.zeros_like(x)
        if normals is not None and not callable(normals) and not isinstance(normals, str) \
                and not _is_cad(normals):
            arr = np.asarray(normals, dtype=float)
            if arr.ndim != 2 or arr.shape[0] != len(pts) or arr.shape[1] not in (2, 3):
                raise ValueError(
                    f"normals array must have shape (num_points={len(pts)}, 2 or 3), got {arr.shape}"
                )
            user[..., : arr.shape[1]] = arr[fac]
        elif _is_cad(normals):
            user = _cad_vertex_normals(normals, x, fac, np.isin(tag, self.tags))
        self._build(fac, x, tag, fn, user, normals, crease_angle, split_tags, eps)
        return self

    def _build(self, gids, coords, tag, fnorm, user, normals, crease_angle, split_tags, eps):
        """Canonical ordering, corner normals and edge coefficients from gathered arrays."""
        tags = self.tags
        # canonical order: vertex ids sorted within facets, facets sorted lexicographically
        perm = np.argsort(gids, axis=1)
        gids = np.take_along_axis(gids, perm, axis=1)
        coords = np.take_along_axis(coords, perm[:, :, None], axis=1)
        user = np.take_along_axis(user, perm[:, :, None], axis=1)
        order = np.lexsort(gids.T[::-1])
        gids, coords, tag, fnorm, user = gids[order], coords[order], tag[order], fnorm[order], user[order]
        if not np.all(np.isfinite(coords)):
            raise ValueError("the coarse mesh has NaN or infinite boundary coordinates")
        if len(gids) > 1 and np.any(np.all(gids[1:] == gids[:-1], axis=1)):
            raise ValueError("a boundary facet appears twice in the gathered coarse boundary")
        _check_facet_area(fnorm, coords)
        snap = np.isin(tag, tags)
        _check_coincident(gids, coords, snap)
        _, vid = np.unique(gids, return_inverse=True)
        vid = vid.reshape(gids.shape)
        self.ids = gids
        self.x = coords
        self.tag = tag
        self.facet_normal = fnorm
        scheme = normals if isinstance(normals, str) else "jet"
        cn = corner_normals(vid, coords, fnorm, tag, crease_angle, split_tags, scheme)
        if not self._KEEP_RINGS:
            cn.rings = None  # the jets' stencils: memory only a geometry fitting on them needs
        n = cn.normals.copy()
        self.snap = snap
        if _is_cad(normals):  # orientation is free: aligned with the estimate
            dot = np.einsum("fvi,fvi->fv", user[snap], n[snap])
            n[snap] = np.where(dot[..., None] < 0, -user[snap], user[snap])
        elif normals is not None and not isinstance(normals, str):
            n[snap] = self._supplied_normals(normals, coords[snap], user[snap], n[snap], crease_angle)
        n, crease = _sector_consistent(cn, n)
        self.corner_normal = n
        # the sector and ridge structure, for geometries built on these patches (FittedGeometry)
        self.corners, self.crease = cn, crease
        self.coef = self._edge_coefficients(cn, n, crease, eps)

    @staticmethod
    def _supplied_normals(normals, coords: np.ndarray, user: np.ndarray, est: np.ndarray,
                          crease_angle: float) -> np.ndarray:
        """User normals (callable of position or array) at the snapped corners, ``(ns, nfv, 3)``.

        Orientation is free (aligned with the estimate ``est``); corners where
        the supplied normal is more than ``crease_angle`` from the estimate
        keep the estimate, with a warning.
        """
        nfv = coords.shape[1]
        if callable(normals):
            pts = coords.reshape(-1, 3)
            val = np.asarray(normals(pts), dtype=float)
            if val.shape == (len(pts), 2):
                val = np.c_[val, np.zeros(len(pts))]
            if val.shape != (len(pts), 3):
                raise ValueError(
                    f"normals callable returned shape {val.shape}, expected ({len(pts)}, 3)"
                )
            un = val.reshape(-1, nfv, 3)
        else:
            un = user
        un = _unit(un, "user-supplied", coords)
        # orientation is free (Nagata's c(d, n0, n1) is unchanged when both
        # normals flip): align each with the outward estimate
        dot = np.einsum("fvi,fvi->fv", un, est)
        un = np.where(dot[..., None] < 0, -un, un)
        far = np.abs(dot) < np.cos(np.radians(crease_angle))
        if far.any():
            warnings.warn(
                f"{int(far.sum())} supplied normals differ from the estimated normal of "
                f"their facet side by more than {crease_angle} deg (other side of a "
                "crease?); the estimated normal is kept there",
                stacklevel=4,
            )
        return np.where(far[..., None], est, un)

    # ------------------------------------------------------------------
    def _edge_coefficients(self, cn, n: np.ndarray, crease: np.ndarray, eps: float) -> np.ndarray:
        x = self.x
        nfv = self.ids.shape[1]
        if nfv == 2:
            cos = np.einsum("fi,fi->f", n[:, 0], n[:, 1])
            self._check_opposite(cos)
            return patches.curve_coefficient(x[:, 1] - x[:, 0], n[:, 0], n[:, 1], eps)[:, None, :]
        local = patches.LOCAL_EDGES[3]
        a, b = local[:, 0], local[:, 1]
        d = x[:, b] - x[:, a]  # (F, 3, 3)
        n0, n1 = n[:, a], n[:, b]
        cos = np.einsum("fei,fei->fe", n0, n1)
        self._check_opposite(cos)
        coef = patches.curve_coefficient(d, n0, n1, eps)
        # crease ridges: one coefficient from all normals of both facets (eq. 32)
        cr = np.flatnonzero(crease)
        if len(cr):
            rf = cn.ridge_facets[cr]  # (R, 2)
            rv = cn.ridge_vertices[cr]  # (R, 2) vertex ids, sorted
            vid = cn.vertex
            # local positions of the ridge's two vertices in each of its facets
            pos = np.stack(
                [np.argmax(vid[rf[:, s]][:, :, None] == rv[:, None, :], axis=1) for s in (0, 1)],
                axis=1,
            )  # (R, 2 facets, 2 ends)
            N0 = np.stack([n[rf[:, s], pos[:, s, 0]] for s in (0, 1)], axis=1)
            N1 = np.stack([n[rf[:, s], pos[:, s, 1]] for s in (0, 1)], axis=1)
            dr = x[rf[:, 0], pos[:, 0, 1]] - x[rf[:, 0], pos[:, 0, 0]]
            cm = patches.curve_coefficient_multi(dr, N0, N1, eps)
            # write into the local edge slot of each facet
            for s in (0, 1):
                p = np.sort(pos[:, s], axis=1)
                slot = np.where(
                    (p[:, 0] == 0) & (p[:, 1] == 1), 0, np.where((p[:, 0] == 1) & (p[:, 1] == 2), 1, 2)
                )
                coef[rf[:, s], slot] = cm
        return coef

    @staticmethod
    def _check_opposite(cos: np.ndarray) -> None:
        bad = cos < -0.9
        if bad.any():
            raise NormalsError(
                f"{int(bad.sum())} boundary edges have end normals more than "
                f"{np.degrees(np.arccos(-0.9)):.0f} degrees apart (opposite normals on "
                "neighbouring vertices); check the supplied normals or the crease angle"
            )

    # ------------------------------------------------------------------
    @property
    def num_patches(self) -> int:
        """Number of coarse boundary facets (patches), over all processes."""
        return int(self.ids.shape[0])

    def find(self, gids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Canonical patch of facets given by input-global vertex ids.

        Args:
            gids: ``(nf, nfv)`` input-global vertex indices (any order per row).

        Returns:
            ``(patch, perm)``: ``(nf,)`` patch index (-1 if not a coarse
            boundary facet) and ``(nf, nfv)`` position of each given vertex in
            the patch's canonical vertex order.
        """
        perm = np.argsort(gids, axis=1)
        key = np.take_along_axis(gids, perm, axis=1)
        patch = _rows_searchsorted(self.ids, key)
        inv = np.argsort(perm, axis=1)
        return patch, inv

    def attach(
        self, points: np.ndarray, nodes: np.ndarray | None = None, *, comm: MPI.Comm | None = None
    ) -> Records:
        """Records of coarse-mesh facets: their own patch and vertex barycentrics.

        Collective on the communicator of the mesh the geometry was built on.

        Args:
            points: ``(nf, nfv, 3)`` facet vertex coordinates (used to verify).
            nodes: ``(nf, nfv)`` input-global vertex indices of the facets.
            comm: unused (for :class:`~nagata_snap.geometry.SnapGeometry`): the
                patches are identical on every process, and the checks reduce
                over the geometry's own communicator.

        Returns:
            :class:`Records` with ``params`` the permutation matrices that map
            each local vertex to the patch's canonical vertex.
        """
        if nodes is None:
            raise ValueError("NagataGeometry.attach needs the facets' input-global vertex ids")
        patch, inv = self.find(np.asarray(nodes, dtype=np.int64))
        # collective decisions: every process raises, or none does
        n_missing = self.comm.allreduce(int(np.sum(patch < 0)))
        if n_missing:
            raise ValueError(
                f"{n_missing} facets are not boundary facets of the mesh this NagataGeometry "
                "was built on (build the geometry and the Snapper on the same coarse mesh)"
            )
        nfv = inv.shape[1]
        params = np.eye(nfv)[inv]
        same = np.all(
            np.asarray(points) == self.x[patch][np.arange(len(patch))[:, None], inv], axis=(1, 2)
        )
        n_moved = self.comm.allreduce(int(np.sum(~same)))
        if n_moved:
            raise ValueError(
                f"the coordinates of {n_moved} facets differ from the mesh this NagataGeometry was "
                "built on (was the mesh moved after the geometry was built?)"
            )
        return Records(patch.astype(np.int64), params)

    def place(
        self, records: Records, straight: np.ndarray | None = None
    ) -> tuple[np.ndarray, Records, PlaceReport]:
        """Evaluate each facet vertex on its coarse facet's Nagata patch.

        Args:
            records: records of ``nf`` facets (``params`` barycentric, ``(nf, nfv, nfv)``).
            straight: unused (Nagata placement needs no projection).

        Returns:
            ``(points (nf, nfv, 3), records, report)``.
        """
        r = records.root
        pts = patches.evaluate(self.x[r], self.coef[r], records.params)
        return pts, records, PlaceReport(n_points=int(pts.shape[0] * pts.shape[1]))

    def project(self, records: Records, points: np.ndarray) -> tuple[np.ndarray, Records]:
        """Closest points on each facet's own coarse patch, seeded by the records.

        Every facet vertex (slot) is projected onto the Nagata patch of its
        record's coarse facet (:func:`~nagata_snap.nagata.patch.closest_on_patch`,
        Newton from the record's barycentrics), and stays inside that facet:
        a slot whose record has one zero barycentric coordinate lies on a
        coarse edge (shared with the neighbouring patch, or a crease) and
        moves along that edge's curve only; two zeros (a coarse vertex, e.g.
        a corner) never move.  In 2D a curve slot moves along its curve, a
        coarse vertex does not.  A patch slot whose closest point lies outside
        the triangle continues on the nearest edge.  So the same vertex gets
        the same point from the slots of both patches that share its edge.

        Args:
            records: records of ``nf`` facets (``params`` barycentric, ``(nf, nfv, nfv)``).
            points: ``(nf, nfv, 3)`` points to project, one per slot.

        Returns:
            ``(points (nf, nfv, 3), records)``: the closest points (each an
            evaluation of its new record) and records with the new barycentrics
            (zero coordinates stay exactly zero).
        """
        pts = np.asarray(points, dtype=float)
        lam = np.array(records.params, dtype=float)
        nf, nfv = lam.shape[:2]
        if pts.shape != (nf, nfv, 3):
            raise ValueError(f"points must have shape ({nf}, {nfv}, 3), got {pts.shape}")
        root = np.repeat(np.asarray(records.root), nfv)
        lam = lam.reshape(nf * nfv, nfv)
        p = pts.reshape(-1, 3)
        nz = np.count_nonzero(lam == 0.0, axis=1)
        if nfv == 3:
            inner = np.flatnonzero(nz == 0)
            r = root[inner]
            lam[inner] = patches.closest_on_patch(self.x[r], self.coef[r], lam[inner], p[inner])
            # off the triangle: drop the most negative coordinate, go on along that edge
            out = inner[lam[inner].min(axis=1) < 0.0]
            lam[out, np.argmin(lam[out], axis=1)] = 0.0
            edge = np.flatnonzero(np.count_nonzero(lam == 0.0, axis=1) == 1)
        else:
            edge = np.flatnonzero(nz == 0)
        if edge.size:
            lam[edge] = self._closest_on_edge(root[edge], lam[edge], p[edge])
        new = Records(np.asarray(records.root).copy(), lam.reshape(nf, nfv, nfv))
        return self.evaluate(root, lam[:, None, :])[:, 0].reshape(nf, nfv, 3), new

    def _closest_on_edge(self, patch: np.ndarray, lam: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Barycentrics ``(k, nfv)`` of the closest points on the patch edge of the nonzero ``lam``."""
        k, nfv = lam.shape
        if nfv == 2:
            a, b, slot = np.zeros(k, int), np.ones(k, int), np.zeros(k, int)
        else:
            zero = np.argmax(lam == 0.0, axis=1)  # the coordinate that stays 0
            a = np.where(zero == 0, 1, 0)
            b = np.where(zero == 2, 1, 2)
            slot = np.where(zero == 2, 0, np.where(zero == 0, 1, 2))  # LOCAL_EDGES order
        rows = np.arange(k)
        xs = self.x[patch]
        la, lb = lam[rows, a], lam[rows, b]
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = np.where(la + lb > 0, lb / (la + lb), 0.5)
        t = patches.closest_on_curve(xs[rows, a], xs[rows, b], self.coef[patch, slot], t0, p)
        out = np.zeros_like(lam)
        out[rows, a] = 1.0 - t
        out[rows, b] = t
        return out

    def evaluate(self, patch: npt.ArrayLike, lam: np.ndarray) -> np.ndarray:
        """Points on patches ``patch (P,)`` at barycentric ``lam (P, k, nfv)``: ``(P, k, 3)``."""
        patch = np.asarray(patch)
        return patches.evaluate(self.x[patch], self.coef[patch], lam)


def _cad_vertex_normals(cad, coords: np.ndarray, gids: np.ndarray, snap: np.ndarray) -> np.ndarray:
    """Unit CAD normals ``(nf, nfv, 3)`` at the corners of the ``snap`` facets, zero elsewhere.

    Each snapped facet ``coords (nf, nfv, 3)`` (vertex ids ``gids (nf, nfv)``)
    is attached to its own CAD face (``cad.attach``) and gets that face's
    normals at its vertices (``cad.vertex_normals``), whatever the normals of
    the neighbouring faces at the same vertex.
    """
    out = np.zeros_like(coords)
    if not snap.any():
        return out
    val = np.asarray(cad.vertex_normals(cad.attach(coords[snap], gids[snap])), dtype=float)
    if val.shape != coords[snap].shape:
        raise ValueError(
            f"the CAD geometry's vertex_normals returned shape {val.shape}, expected {coords[snap].shape}"
        )
    out[snap] = _unit(val, "CAD", coords[snap])
    return out


def _sector_consistent(cn, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One normal per sector where supplied normals allow it; creases where they differ.

    Corners of one sector whose normals differ (per-facet CAD normals of two
    faces meeting tangentially) get their mean when they are at most
    :data:`SECTOR_MERGE_DEG` apart; a smooth ridge whose two facets still
    carry different normals at a common vertex is then treated as a crease
    (the multi-normal coefficient uses both facets' normals alike, so the
    patches keep sharing the edge curve).

    Returns:
        ``(normals (F, nfv, 3), crease (R,))``.
    """
    F, nfv = cn.sector.shape
    lab = cn.sector.ravel()
    flat = n.reshape(-1, 3)
    mean = np.zeros((lab.max() + 1, 3))
    np.add.at(mean, lab, flat)
    mean /= np.linalg.norm(mean, axis=1, keepdims=True)
    cos = np.ones(len(mean))
    np.minimum.at(cos, lab, np.einsum("ci,ci->c", flat, mean[lab]))
    differ = np.zeros(len(mean), dtype=bool)
    np.logical_or.at(differ, lab, np.any(flat != flat[np.unique(lab, return_index=True)[1]][lab], axis=1))
    merge = differ & (cos >= np.cos(np.radians(SECTOR_MERGE_DEG)))
    flat = np.where(merge[lab, None], mean[lab], flat)
    n = flat.reshape(F, nfv, 3)
    rf, crease = cn.ridge_facets, cn.crease.copy()
    vid = cn.vertex
    for k in range(cn.ridge_vertices.shape[1]):  # the ridge's vertices (1 in 2D, 2 in 3D)
        pos = [np.argmax(vid[rf[:, s]] == cn.ridge_vertices[:, k, None], axis=1) for s in (0, 1)]
        crease |= np.any(n[rf[:, 0], pos[0]] != n[rf[:, 1], pos[1]], axis=1)
    return n, crease


def _rows_searchsorted(table: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Index of each row of ``rows`` in the lexicographically sorted ``table`` (-1 if absent)."""
    if len(table) == 0:
        return np.full(len(rows), -1)
    t = np.ascontiguousarray(table)
    r = np.ascontiguousarray(rows)
    dt = np.dtype((np.void, t.dtype.itemsize * t.shape[1]))
    # void-view comparison is bytewise, not numeric: sort a view of the table
    tv = t.view(dt).ravel()
    rv = r.view(dt).ravel()
    order = np.argsort(tv)
    pos = np.searchsorted(tv[order], rv)
    pos = np.minimum(pos, len(tv) - 1)
    hit = tv[order][pos] == rv
    return np.where(hit, order[pos], -1)
