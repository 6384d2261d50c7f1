"""Fitted geometry: a CAD-free surface of order ``p + 1`` from local fits blended over the coarse facets.

:class:`FittedGeometry` is built from the same coarse boundary as
:class:`~nagata_snap.nagata.geometry.NagataGeometry` (it is one: the boundary
gathered on every process in canonical order, creases, sectors and the
estimated normals, the records and the sliding projection's seeds are all
Nagata's) and replaces the surface (after Jiao & Wang 2012, WALF):

* every smooth sector of every coarse vertex gets a weighted least-squares
  height fit of degree ``p`` in the frame of its estimated normal, over the
  vertices of its own smooth region within a few facet rings
  (:mod:`nagata_snap.fitted.fit`);
* a point of coarse facet ``f`` at barycentric ``lambda`` is
  ``sum_i lambda_i q_i``, ``q_i`` the fit of corner ``i``'s sector evaluated
  at the straight point's projection into that sector's frame.  Vertices are
  interpolated, and a point of an edge depends only on the edge's two vertex
  fits: C0 across smooth coarse edges;
* a crease (a sharp ridge, or one between tags with ``split_tags``) is a
  space curve fitted at each of its end vertices through the vertices along
  the crease (stopping at corners, where three or more creases meet or one
  ends), blended the same way along the edge; the facets on both sides add
  ``(lambda_a + lambda_b) (C(t) - S(t))``, the gap between the curve and
  their own blend on that edge at ``t = lambda_b / (lambda_a + lambda_b)``,
  which vanishes on their other edges: both sides meet on the one curve,
  corners (vertices) stay fixed;
* a sector whose fit is not exact and that meets a better-fitted sector
  tangentially (a fillet's torus corner beside a plane or a cylinder) is
  refitted with that sector's normals as slope equations, at up to degree
  ``p + 2`` (:meth:`FittedGeometry._hermite_refit`);
* a fit that disagrees with its neighbours' (a stencil too coarse or ragged
  for the degree) gives way to the Nagata patch at its corners, a crease
  chain too short for a fit of order 3 (between close corners) or a crease
  fit straying from Nagata's crease curve to that curve (:data:`GUARD`);
* the departure from the straight facet is bounded by :data:`FIT_BOUND`
  times the ``lambda``-weighted mean edge length at the facet's vertices (a
  function of the point alone, so the bound keeps the surface C0), as
  ``B_MAX`` bounds Nagata's coefficients: a noisy or too coarse stencil
  cannot fold a patch.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import dolfinx.mesh
import numpy as np
import numpy.typing as npt

from nagata_snap.fitted.fit import (
    _weights,
    blend_kernel,
    fit_curves,
    fit_levels,
    fit_surfaces,
    plane_value,
    surface_height,
    term_columns,
    terms,
)
from nagata_snap.geometry import PlaceReport
from nagata_snap.mesh.records import Records
from nagata_snap.nagata import patch as patches
from nagata_snap.nagata.geometry import NagataGeometry, NormalSource
from nagata_snap.nagata.jets import SectorRings, _frame

__all__ = ["FittedGeometry", "DEGREES", "FIT_BOUND"]

#: Supported fit degrees.
DEGREES = range(2, 7)

#: Largest distance of the fitted surface from the straight facet, in units of
#: the ``lambda``-weighted mean edge length at the facet's vertices (a sphere
#: meshed with 6 facets around a vertex departs by about 0.15 of it).
FIT_BOUND = 0.5

#: A sector's fit is refused (its corners use the Nagata patch) where it
#: disagrees with a neighbouring corner's fit by more than ``GUARD`` times the
#: smaller of the patch's departure from the straight facet and the fits'
#: correction of the patch there (:meth:`FittedGeometry._guard`): fits that
#: disagree by as much as they move the patch are no evidence of doing better
#: than it.  A crease's fitted curve is refused where it differs from the
#: Nagata crease curve by more than ``GUARD`` times that curve's departure from
#: the chord.
GUARD = 0.5

#: Hermite refits (:meth:`FittedGeometry._hermite_refit`): sectors at a vertex are tangent where
#: their fitted normals agree within this angle (degrees) ...
HERMITE_ANGLE = 10.0
#: ... a sector takes the normal of a sector there whose residual is at most this fraction of its own ...
HERMITE_RATIO = 0.1
#: ... and is refitted at up to this much above the requested degree (at most 6): each point with a
#: normal gives three equations, and a degree-4 fit over a torus corner 4 facets wide was no better than
#: the patch.
HERMITE_EXTRA = 2
#: ... where its own residual (weighted RMS misfit over its stencil relative to the stencil's RMS
#: height) exceeds this: fits that are not exact (quadrics: 1e-14 and less; the plate's torus corners:
#: 1e-6 and more) ...
HERMITE_MIN_RESIDUAL = 1e-8
#: Weight of a point's two slope equations relative to its position's (1 and 10 were 2x and 6x less
#: accurate on the filleted plate's torus corners than 0.3; 0.03 1.7x).
SLOPE_WEIGHT = 0.3

#: Barycentric samples of the guard, per facet size (2D: segments, 3D: triangles).
GUARD_SAMPLES = {
    2: np.array([[0.75, 0.25], [0.5, 0.5], [0.25, 0.75]]),
    3: np.array([[0.5, 0.5, 0.0], [0.5, 0.0, 0.5], [0.0, 0.5, 0.5], [4 / 6, 1 / 6, 1 / 6], [1 / 6, 4 / 6, 1 / 6],
                 [1 / 6, 1 / 6, 4 / 6], [1 / 3, 1 / 3, 1 / 3]]),
}


def check_degree(degree: object) -> int:
    """``degree`` as an int, or a ``ValueError`` naming the supported range."""
    if isinstance(degree, bool) or not isinstance(degree, int | np.integer) or int(degree) not in DEGREES:
        raise ValueError(
            f"degree must be an integer from {DEGREES.start} to {DEGREES.stop - 1} (the fits' polynomial "
            f"degree; 4 is the default), got {degree!r}"
        )
    return int(degree)


def _rings(degree: int, planar: bool) -> int:
    """Stencil width (facet rings) of a two-sided fit of ``degree``: the fewest with enough points.

    3D: ``r`` rings of a regular mesh hold ``3 r (r + 1)`` vertices; 2D: ``2 r``.
    """
    need = terms(degree, planar) + 2
    r = 1
    while (2 * r if planar else 3 * r * (r + 1)) < need:
        r += 1
    return max(r, 2)


class FittedGeometry(NagataGeometry):
    """High-order fitted surface over the tagged boundary facets of a coarse mesh (no CAD).

    Args:
        mesh, facet_tags, tags, normals, crease_angle, split_tags, eps: as for
            :class:`~nagata_snap.nagata.geometry.NagataGeometry` (the fits' frames
            are its corner normals: estimated by default).
        degree: polynomial degree ``p`` of the local fits, 2 to 6 (default 4):
            the surface converges at order about ``p + 1`` on smooth parts.

    Attributes:
        degree: the requested degree.
        fit_degree: ``(S,)`` degree each sector's fit got (lower where its
            stencil was too small; :meth:`fit_summary`).
        n_clipped: points of the last :meth:`evaluate` whose departure from
            the straight facet was bounded (:data:`FIT_BOUND`).

    Raises:
        ValueError: a ``degree`` out of range, and as ``NagataGeometry``.
    """

    degree: int
    _KEEP_RINGS = True  # the fits' stencils grow from the jets' rings

    def __init__(
        self,
        mesh: dolfinx.mesh.Mesh,
        facet_tags: dolfinx.mesh.MeshTags,
        tags: Sequence[int] | None = None,
        *,
        degree: int = 4,
        normals: NormalSource = None,
        crease_angle: float = 60.0,
        split_tags: bool = True,
        eps: float = patches.EPS,
    ):
        self.degree = check_degree(degree)
        super().__init__(mesh, facet_tags, tags, normals=normals, crease_angle=crease_angle,
                         split_tags=split_tags, eps=eps)
        self._fit()

    @classmethod
    def from_surface(
        cls,
        points: npt.ArrayLike,
        facets: npt.ArrayLike,
        facet_tags: npt.ArrayLike | None = None,
        tags: Sequence[int] | None = None,
        *,
        degree: int = 4,
        normals: NormalSource = None,
        crease_angle: float = 60.0,
        split_tags: bool = True,
        eps: float = patches.EPS,
    ) -> FittedGeometry:
        """Fitted surface over a closed polygon (2D) or triangulated surface (3D), without a mesh.

        Arguments as :meth:`NagataGeometry.from_surface
        <nagata_snap.nagata.geometry.NagataGeometry.from_surface>`, plus ``degree``.
        """
        d = check_degree(degree)
        self = super().from_surface(points, facets, facet_tags, tags, normals=normals,
                                    crease_angle=crease_angle, split_tags=split_tags, eps=eps)
        assert isinstance(self, FittedGeometry)
        self.degree = d
        self._fit()
        return self

    # ------------------------------------------------------------------
    def _fit(self) -> None:
        """Sector height fits and crease curve fits from the gathered coarse boundary."""
        cn = self.corners
        vid, label = cn.vertex, cn.sector
        nfv = vid.shape[1]
        planar = nfv == 2
        coords = np.zeros((int(vid.max()) + 1, 3))
        coords[vid.ravel()] = self.x.reshape(-1, 3)
        S = int(label.max()) + 1
        centre = np.zeros(S, dtype=np.int64)
        centre[label.ravel()] = vid.ravel()
        normal = np.zeros((S, 3))
        normal[label.ravel()] = self.corner_normal.reshape(-1, 3)
        # mean edge length at each vertex: the fits' length scale and the departure bound's
        pairs = patches.LOCAL_EDGES[nfv]
        le = np.linalg.norm(self.x[:, pairs[:, 1]] - self.x[:, pairs[:, 0]], axis=2).ravel()
        ends = vid[:, pairs].reshape(-1, 2)
        hv = np.bincount(ends.ravel(), np.repeat(le, 2), minlength=len(coords)) / np.maximum(
            np.bincount(ends.ravel(), minlength=len(coords)), 1)
        if planar:
            t1 = np.stack([-normal[:, 1], normal[:, 0], np.zeros(S)], axis=1)
            t2 = np.zeros_like(t1)
        else:
            t1, t2 = _frame(normal)
        frame = np.stack([t1, t2, normal], axis=1)
        r0 = _rings(self.degree, planar)
        widths = (r0, 2 * r0) if planar else (r0, r0 + 1)
        # implicit fits, then height polynomials where no implicit fit is a height function
        levels = [(d, w, e) for e in (False, True) for d in range(self.degree, 1, -1) for w in widths]

        rings = cn.rings if cn.rings is not None else SectorRings(vid, label, cn.region)

        def stencil(width: int, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            idx, mask = rings.stencils(width, rows=None if len(rows) == S else rows)
            return idx, mask & (idx != centre[:, None])

        def fit(sel, idx, mask, d, explicit):
            c = centre[sel]
            return fit_surfaces(coords[c], frame[sel], coords[idx], mask, hv[c], d, planar, explicit)[:, None, :]

        # the evaluation degree: Hermite refits (3D) may go up to HERMITE_EXTRA above ``degree``
        top = self.degree if planar else min(self.degree + HERMITE_EXTRA, DEGREES.stop - 1)
        coef, self.fit_degree, level = fit_levels(
            levels, stencil, fit, S, lambda d: term_columns(d, top, planar), terms(top, planar))
        self._top = top
        self.n_hermite = 0
        if not planar:
            self._hermite_refit(coef, stencil, coords, frame, centre, hv, r0)
        if int(self.fit_degree.max(initial=0)) <= self.degree < top:  # no refit above degree: drop the padding
            coef = coef[..., term_columns(self.degree, top, planar)]
            self._top = self.degree
        cn.rings = None  # their memory
        self.fit_explicit = (level >= 0) & np.array([e for _, _, e in levels])[np.maximum(level, 0)]
        self._coords, self._hv, self._frame_s, self._coef_s = coords, hv, frame, coef[:, 0]
        self._planar = planar
        # planar stencils' fits (fit_surfaces' FLAT): the tangent plane, which holds their facets
        self._flat = (self.fit_degree > 0) & ~self._coef_s.any(axis=1)
        # each sector's fit is evaluated up to its own degree (its terms above are zero)
        self._eval_degree = np.maximum(self.fit_degree, 2).astype(np.int64)
        self.n_clipped = 0
        self._use_nagata = np.zeros(S, dtype=bool)
        self._fit_creases(coords, hv)
        self._use_nagata = self._guard()

    def _hermite_refit(self, coef: np.ndarray, stencil: Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]],
                       coords: np.ndarray, frame: np.ndarray, centre: np.ndarray, hv: np.ndarray, r0: int) -> None:
        """Refit (in ``coef (S, 1, q)``) the sectors that meet a better-fitted sector tangentially, with its normals.

        A face a few facets wide between tangency (G1) lines (a fillet's torus
        corner: 3-6 segments over 90 degrees each way) gives one-sided stencils
        spanning the face, and fits worse than the Nagata patch.  Where such a
        line is shared with a sector whose fit reproduces its stencil better
        (a plane, a cylinder: exact), that sector's fitted normal is the
        surface's normal on the line too (the faces are tangent there).  Each
        vertex where all sectors' fitted normals agree within
        :data:`HERMITE_ANGLE` takes the normal of its sector of least residual
        (the weighted RMS of its implicit fit over its stencil); a sector
        whose own residual is at least ``1 / HERMITE_RATIO`` times that gets
        slope equations there (:func:`~nagata_snap.fitted.fit.slope_rows`: at
        its own vertex and its stencil points), three equations per point
        instead of one, and is refitted at up to ``degree + HERMITE_EXTRA``
        (then lower) over the same stencil widths.  Surfaces of one sector per
        vertex (no tangency lines) are not touched.
        """
        S, q = len(centre), coef.shape[-1]
        V = len(coords)
        c0 = coef[:, 0]
        nsec = np.bincount(centre, minlength=V)
        idx, mask = stencil(r0, np.arange(S))
        # sectors that meet another at their vertex or in their stencil, and have a fit that is not planar
        near = ((nsec[idx] >= 2) & mask).any(axis=1) | (nsec[centre] >= 2)
        cand = np.flatnonzero(near & c0.any(axis=1))
        if len(cand) == 0:
            return
        resid = np.where(self.fit_degree > 0, 0.0, np.inf)  # planar fits: 0
        resid[cand] = self._residual(c0[cand], coords, frame[cand], centre[cand], hv, idx[cand], mask[cand])
        g = frame[:, 2] + c0[:, q - 2, None] * frame[:, 0] + c0[:, q - 1, None] * frame[:, 1]
        nfit = g / np.linalg.norm(g, axis=1, keepdims=True)
        # each vertex's best-fitted sector, and whether all its sectors are tangent to it
        order = np.lexsort((resid, centre))
        first = np.r_[True, centre[order][1:] != centre[order][:-1]]
        best = np.zeros(V, dtype=np.int64)
        best[centre[order][first]] = order[first]
        cosmin = np.ones(V)
        np.minimum.at(cosmin, centre, np.einsum("si,si->s", nfit, nfit[best[centre]]))
        ok = (nsec >= 2) & (cosmin >= np.cos(np.radians(HERMITE_ANGLE))) & np.isfinite(resid[best])
        hres = np.where(ok, resid[best], np.inf) / HERMITE_RATIO
        hn = nfit[best]

        def known(sel: np.ndarray, pts: np.ndarray, m: np.ndarray) -> np.ndarray:
            """``(len(sel), k)`` whether sectors ``sel`` take a Hermite normal at vertices ``pts``."""
            return m & (hres[pts] <= resid[sel][:, None])

        def normals_at(sel: np.ndarray, pts: np.ndarray, m: np.ndarray) -> np.ndarray:
            """``(len(sel), k, 3)`` the Hermite normals of sectors ``sel`` at vertices ``pts``, NaN where none."""
            return np.where(known(sel, pts, m)[..., None], hn[pts], np.nan)

        with_c = np.c_[centre[cand], idx[cand]], np.c_[np.ones(len(cand), dtype=bool), mask[cand]]
        has = known(cand, *with_c).any(axis=1)
        redo = cand[has & (resid[cand] > HERMITE_MIN_RESIDUAL)]
        if len(redo) == 0:
            return
        levels = [(d, w, False) for d in range(self._top, 1, -1) for w in (r0, r0 + 1)]

        def stencil2(width: int, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            i2, m2 = stencil(width, redo[rows])
            return i2[redo], m2[redo]

        def count(i2: np.ndarray, m2: np.ndarray) -> np.ndarray:
            nh = known(redo, np.c_[centre[redo], i2], np.c_[np.ones(len(redo), dtype=bool), m2])
            return m2.sum(axis=1) + 2 * nh.sum(axis=1)

        def fit2(sel: np.ndarray, i2: np.ndarray, m2: np.ndarray, dd: int, explicit: bool) -> np.ndarray:
            s, c = redo[sel], centre[redo[sel]]
            N = normals_at(s, np.c_[c, i2], np.c_[np.ones(len(sel), dtype=bool), m2])
            return fit_surfaces(coords[c], frame[s], coords[i2], m2, hv[c], dd, False, explicit, normals=N,
                                slope_weight=SLOPE_WEIGHT)[:, None, :]

        coef2, deg2, _ = fit_levels(levels, stencil2, fit2, len(redo), lambda d: term_columns(d, self._top, False),
                                    terms(self._top, False), equations=count)
        done = deg2 > 0
        coef[redo[done]] = coef2[done]
        self.fit_degree[redo[done]] = deg2[done]
        self.n_hermite = int(done.sum())

    def _residual(self, c: np.ndarray, coords: np.ndarray, frame: np.ndarray, centre: np.ndarray, hv: np.ndarray,
                  idx: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """``(S,)`` weighted RMS of the implicit fits ``c (S, q)`` over their stencils ``idx, mask``, relative to
        the weighted RMS height of the stencil points (0 on the model's surfaces, planes excluded)."""
        loc = np.matmul(coords[idx] - coords[centre][:, None], frame.transpose(0, 2, 1)) / hv[centre][:, None, None]
        u, v, w = loc[..., 0], loc[..., 1], loc[..., 2]
        F = w + plane_value(c, self._top, False, u, v) + (c[:, 3:4] * u + c[:, 4:5] * v + c[:, 5:6] * w) * w
        wt = _weights(u * u + v * v + w * w, np.ones(len(c)), mask)  # (lengths already in units of hv)
        return np.sqrt((wt * F * F).sum(axis=1) / np.maximum((wt * w * w).sum(axis=1), 1e-300))

    def _fit_creases(self, coords: np.ndarray, hv: np.ndarray) -> None:
        """Curve fits at both ends of every crease edge (3D), and each facet edge's crease."""
        cn = self.corners
        vid = cn.vertex
        F, nfv = vid.shape
        self._edge_crease = np.full((F, nfv), -1, dtype=np.int64)  # crease of the edge opposite each corner
        cr = np.flatnonzero(self.crease)
        if nfv == 2 or len(cr) == 0:
            self._crease_ends = np.zeros((0, 2), dtype=np.int64)
            self.curve_degree = np.zeros(0, dtype=np.int64)
            self.curve_circle = np.zeros(0, dtype=bool)
            self._crease_nagata = np.zeros(0, dtype=bool)
            return
        E = cn.ridge_vertices[cr]  # (C, 2) sorted vertex ids
        for s in (0, 1):
            f = cn.ridge_facets[cr, s]
            off = (vid[f][:, :, None] != E[:, None, :]).all(axis=2)
            self._edge_crease[f, np.argmax(off, axis=1)] = np.arange(len(cr))
        a = E.ravel()  # end 2i at E[i, 0] towards E[i, 1], end 2i + 1 the other way
        b = E[:, ::-1].ravel()
        deg = np.bincount(E.ravel(), minlength=len(coords))
        nb = np.full((len(coords), 2), -1, dtype=np.int64)
        two = np.flatnonzero(deg == 2)
        both = np.r_[E[:, 1], E[:, 0]]
        order = np.argsort(np.r_[E[:, 0], E[:, 1]], kind="stable")
        owner = np.r_[E[:, 0], E[:, 1]][order]
        first = np.searchsorted(owner, two)
        nb[two, 0] = both[order][first]
        nb[two, 1] = both[order][first + 1]

        # crease edges by their sorted end vertices, to name each step of a walk
        keys = E[:, 0] * len(coords) + E[:, 1]
        korder = np.argsort(keys)

        def edge_of(u: np.ndarray, v: np.ndarray) -> np.ndarray:
            k = np.minimum(u, v) * len(coords) + np.maximum(u, v)
            return korder[np.minimum(np.searchsorted(keys[korder], k), len(keys) - 1)]

        def walk(prev: np.ndarray, cur: np.ndarray, ok: np.ndarray, steps: int) -> np.ndarray:
            """Edge ends ``2 e + k`` (vertex ``E[e, k]`` reached along crease edge ``e``), -1 past the chain."""
            out = np.full((len(cur), steps), -1, dtype=np.int64)
            for k in range(steps):  # a few steps along the crease, all ends at once
                ok = ok & (cur >= 0) & (cur != a)
                c = np.maximum(cur, 0)
                e = edge_of(np.maximum(prev, 0), c)
                out[:, k] = np.where(ok, 2 * e + (E[e, 1] == c), -1)
                nxt = np.where(nb[c, 0] == prev, nb[c, 1], nb[c, 0])
                ok = ok & (deg[c] == 2)
                prev, cur = cur, nxt
            return out

        back0 = np.where(nb[a, 0] == b, nb[a, 1], nb[a, 0])

        def stencil(width: int, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
            idx = np.c_[walk(a, b, np.ones(len(a), dtype=bool), width),
                        walk(a, back0, deg[a] == 2, width)]
            return np.maximum(idx, 0), idx >= 0

        tangent = coords[b] - coords[a]
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        near, near_ok = stencil(2)
        n1, n2 = self._chain_frame(tangent, coords[a], coords[a[near]], near_ok)
        # the faces' normals on both sides at each edge end (end j = 2 e + k: vertex a[j])
        side_n = self._crease_side_normals(cr, E).reshape(-1, 2, 3)

        def fit(sel, idx, mask, d, circle):
            N = np.concatenate([side_n[sel][:, None], side_n[idx]], axis=1)
            return fit_curves(coords[a[sel]], tangent[sel], (n1[sel], n2[sel]), coords[a[idx]], mask,
                              hv[a[sel]], d, sides=N, circle=circle)

        top = self._curve_top()
        w0 = math.ceil((top + 2) / 2)
        # the last level: a circle through three points (tangency lines: no slope equations)
        levels = [(d, w, False) for d in range(top, 1, -1) for w in (w0, d + 2)] + [(2, w0, True)]
        # per offset: a position for each point, a slope for each point and the end's own
        coef, self.curve_degree, clevel = fit_levels(levels, stencil, fit, len(a), lambda d: term_columns(d, top, True),
                                                terms(top, True), comps=2, equations=lambda _, m: 2 * m.sum(axis=1) + 1)
        self._crease_ends = np.c_[a, b]
        self._curve = (tangent, n1, n2, coef)
        # creases whose chain is too short for a fit of order 3 or more or a circle (between
        # close corners), or whose fit strays from the Nagata crease curve: the Nagata curve
        self.curve_circle = clevel == len(levels) - 1
        ok = (self.curve_degree >= 3) | self.curve_circle
        self._crease_nagata = ~(ok[0::2] & ok[1::2]) | self._curve_guard()

    @staticmethod
    def _chain_frame(tangent: np.ndarray, x0: np.ndarray, pts: np.ndarray, mask: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Offset directions ``(n1, n2)`` ``(S, 3)`` of curve fits at ``x0`` along unit chords ``tangent``.

        ``n2`` the normal of the plane through ``x0`` that best fits the chain's
        points ``pts (S, m, 3)`` (``mask``), ``n1 = n2 x tangent`` in it: a planar
        curve's offset is all along ``n1`` (its circle fit, :func:`fit_curves`);
        an arbitrary frame where the chain is (nearly) straight.
        """
        n1, n2 = _frame(tangent)
        d = np.where(mask[..., None], pts - x0[:, None, :], 0.0)
        _, sv, vt = np.linalg.svd(d)
        b = vt[:, 2] - np.einsum("si,si->s", vt[:, 2], tangent)[:, None] * tangent
        nb = np.linalg.norm(b, axis=1)
        ok = (mask.sum(axis=1) >= 2) & (sv[:, 1] > 1e-6 * np.maximum(sv[:, 0], 1e-300)) & (nb > 0.5)
        b = b / np.where(nb > 0, nb, 1.0)[:, None]
        m = np.cross(b, tangent)
        return np.where(ok[:, None], m, n1), np.where(ok[:, None], b, n2)

    def _crease_side_normals(self, cr: np.ndarray, E: np.ndarray) -> np.ndarray:
        """``(C, 2, 2, 3)``: at each end ``k`` of crease edges ``E (C, 2)``, the corner normals of its two facets."""
        vid, rf = self.corners.vertex, self.corners.ridge_facets[cr]
        out = np.zeros((len(cr), 2, 2, 3))
        for side in (0, 1):
            f = rf[:, side]
            for k in (0, 1):
                out[:, k, side] = self.corner_normal[f, np.argmax(vid[f] == E[:, k, None], axis=1)]
        return out

    def _curve_top(self) -> int:
        """Degree of the crease curve fits: ``degree``, and at least 4 (even): the offsets of a
        rim circle are even in the abscissa, and a cubic fitted over its wide two-sided chain was
        20x less accurate than Nagata's crease curve on the cylinder's rims."""
        return max(self.degree, 4)

    def _curve_guard(self) -> np.ndarray:
        """Creases ``(C,)`` whose fitted curve differs from Nagata's by more than ``GUARD`` of its departure."""
        cr = np.flatnonzero(self.crease)
        f = self.corners.ridge_facets[cr, 0]
        rv, vid = self.corners.ridge_vertices[cr], self.corners.vertex[f]
        t = np.array([0.25, 0.5, 0.75])
        lam = np.zeros((len(cr), len(t), 3))
        pa = np.argmax(vid == rv[:, :1], axis=1)
        pb = np.argmax(vid == rv[:, 1:], axis=1)
        rows = np.arange(len(cr))
        lam[rows, :, pa] = 1.0 - t
        lam[rows, :, pb] = t
        X = np.matmul(lam, self.x[f])
        nag = patches.evaluate(self.x[f], self.coef[f], lam)
        fit = self._crease_curve(np.arange(len(cr)), np.broadcast_to(1.0 - t, (len(cr), len(t))), X)
        tol = GUARD * np.linalg.norm(nag - X, axis=2) + 1e-9 * self._hv[rv[:, :1]]
        return (np.linalg.norm(fit - nag, axis=2) > tol).any(axis=1)

    def fit_summary(self) -> str:
        """Counts of the degrees the sector (and crease-end) fits got, e.g. ``sectors {4: 1200, 3: 8}``."""

        def counts(d: np.ndarray) -> str:
            u, c = np.unique(d, return_counts=True)
            return "{" + ", ".join(f"{int(k)}: {int(n)}" for k, n in zip(u[::-1], c[::-1], strict=True)) + "}"

        text = f"degree {self.degree}: sectors {counts(self.fit_degree)}"
        if self.fit_explicit.any():
            text += f" ({int(self.fit_explicit.sum())} height polynomials)"
        if self._use_nagata.any():
            text += f", {int(self._use_nagata.sum())} sectors on Nagata patches (guard)"
        if len(self.curve_degree):
            text += f", crease ends {counts(self.curve_degree)}"
            if self.curve_circle.any():
                text += f" ({int(self.curve_circle.sum())} circles)"
            if self._crease_nagata.any():
                text += f", {int(self._crease_nagata.sum())} creases on Nagata curves"
        return text

    # ------------------------------------------------------------------
    def _guard(self) -> np.ndarray:
        """Sectors ``(S,)`` whose fit disagrees with a neighbouring corner's by more than :data:`GUARD`.

        At the samples of :data:`GUARD_SAMPLES` of every facet, the point of
        each corner's fit (weight >= 1/4 there) is measured against the fits of
        the facet's other corners: its height above their implicit surface,
        along their normal.  Exact fits agree to their own error, far below
        Nagata's; a fit from a stencil too coarse or too ragged for its degree
        (a face a few facets wide, a coarse mesh of a strongly curved surface)
        departs from its neighbours'.  Where the disagreement exceeds ``GUARD``
        times the Nagata patch's departure from the straight facet, or
        ``GUARD`` times the larger of the two fits' distances from the patch
        point (their correction of it; plus ``1e-9`` of the vertex's mean edge
        length), both sectors use the Nagata patch point instead of their fit
        (the blend stays C0: the patches are).  The second bound refuses fits
        that agree with each other only to about their own correction: on a
        coarse face a few facets wide, fits from one stencil spanning the face
        can agree within the departure bound and still be farther from the
        surface than the patch.
        Facets whose corners all have planar fits (:attr:`_flat`: tangent
        planes of stencils within ``FLAT`` of them, so of each other) agree to
        rounding and are not measured, nor are samples on a crease edge (the
        surface there is the crease curve; on a tangency line with a plane the
        patch's crease curve is the chord, its departure 0, and any
        disagreement there refused both sectors).
        """
        nfv = self.x.shape[1]
        act = np.flatnonzero(~self._flat[self.corners.sector].all(axis=1))
        F = len(act)
        grid = GUARD_SAMPLES[nfv]
        lam = np.broadcast_to(grid, (F, *grid.shape))
        x0 = self.x[act]
        X = np.matmul(lam, x0)
        nag = patches.evaluate(x0, self.coef[act], lam)
        dep = np.linalg.norm(nag - X, axis=2)
        sec, vid = self.corners.sector[act], self.corners.vertex[act]
        frames, h = self._frame_s[sec], self._hv[vid]
        coef = self._coef_s[sec]
        deg = self._eval_degree[sec]

        def along(P: np.ndarray, i: int) -> np.ndarray:
            """``(F, k, 3)`` the move from ``P`` onto corner ``i``'s fit, along its normal."""
            one = np.zeros((F, nfv), dtype=bool)
            one[:, i] = True
            lam_i = np.zeros((F, P.shape[1], nfv))
            lam_i[..., i] = 1.0
            out = np.zeros_like(P)
            blend_kernel(P, lam_i, x0, frames, h, coef, one, deg, self._planar, out)
            return out

        q = [X + along(X, i) for i in range(nfv)]
        # samples on a crease edge: the surface there is the crease curve, not the fits' blend
        on_crease = np.zeros((F, len(grid)), dtype=bool)
        if nfv == 3:
            for k in range(3):
                e = (grid[:, k] == 0) & ((grid > 0).sum(axis=1) == 2)
                on_crease[:, e] = (self._edge_crease[act, k] >= 0)[:, None]
        gain = [np.linalg.norm(qi - nag, axis=2) for qi in q]  # each fit's correction of the patch
        bad = np.zeros(len(self._coef_s), dtype=bool)
        for i in range(nfv):
            for j in range(nfv):
                if i == j:
                    continue
                r = np.linalg.norm(along(q[i], j), axis=2)
                tol = GUARD * np.minimum(dep, np.maximum(gain[i], gain[j])) + 1e-9 * h[:, j, None]
                far = ((r > tol) & (grid[None, :, i] >= 0.25) & ~on_crease).any(axis=1)
                np.logical_or.at(bad, sec[:, i], far)
                np.logical_or.at(bad, sec[:, j], far)
        return bad

    def _blend(self, patch: np.ndarray, lam: np.ndarray, X: np.ndarray) -> np.ndarray:
        """``sum_i lam_i q_i``: corner fits at the straight points ``X (P, k, 3)``.

        Corners of sectors the guard refused (:meth:`_guard`) contribute the
        facet's Nagata patch point instead; corners with planar fits
        (:attr:`_flat`) nothing (their plane holds the facet to ``FLAT``).
        """
        out = np.ascontiguousarray(X, dtype=float).copy()
        label = self.corners.sector[patch]
        nag = self._use_nagata[label]  # (P, nfv)
        use = ~nag & ~self._flat[label]
        if use.any():
            blend_kernel(out.copy(), np.ascontiguousarray(lam, dtype=float), self.x[patch], self._frame_s[label],
                         self._hv[self.corners.vertex[patch]], self._coef_s[label], use, self._eval_degree[label],
                         self._planar, out)
        if nag.any():
            rows = np.flatnonzero(nag.any(axis=1))
            pn = patches.evaluate(self.x[patch[rows]], self.coef[patch[rows]], lam[rows]) - X[rows]
            out[rows] += np.einsum("pkv,pv,pki->pki", lam[rows], nag[rows].astype(float), pn)
        return out

    def _crease_curve(self, crease: np.ndarray, wa: np.ndarray, P: np.ndarray) -> np.ndarray:
        """Points ``(P, k, 3)`` of creases ``crease (P,)`` at weights ``wa (P, k)`` of their first vertex."""
        tangent, n1, n2, coef = self._curve
        out = np.zeros_like(P)
        for e, w in ((2 * crease, wa), (2 * crease + 1, 1.0 - wa)):
            a = self._crease_ends[e, 0]
            h = self._hv[a][:, None]
            d = P - self._coords[a][:, None, :]
            s = np.einsum("pki,pi->pk", d, tangent[e]) / h
            y1, y2 = (surface_height(coef[e, j], self._curve_top(), True, s, 0.0 * s) for j in (0, 1))
            c = (self._coords[a][:, None, :] + (s * h)[..., None] * tangent[e][:, None, :]
                 + (y1 * h)[..., None] * n1[e][:, None, :] + (y2 * h)[..., None] * n2[e][:, None, :])
            out += w[..., None] * c
        return out

    def _crease_edge(self, p: np.ndarray, lam: np.ndarray, k: int) -> tuple[np.ndarray, ...]:
        """Where points ``lam (P, k, 3)`` of facets ``p`` fall on their crease edge opposite corner ``k``.

        Returns ``(wsum, t, curve, L)``: the edge's weight ``lambda_a + lambda_b``
        ``(P, k)``, the position ``t = lambda_b / wsum`` along the edge from its
        corner ``a = k + 1``, the crease curve's point there ``(P, k, 3)`` (fitted,
        or the Nagata patch's edge where :attr:`_crease_nagata`) and the edge's
        straight vector from ``a`` to ``b`` ``(P, 3)``.
        """
        ia, ib = (k + 1) % 3, (k + 2) % 3
        la, lb = lam[..., ia], lam[..., ib]
        wsum = la + lb
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.where(wsum > 0, lb / wsum, 0.0)
        le = self._edge_lam(t, k)
        Xe = np.matmul(le, self.x[p])
        c = self._edge_crease[p, k]
        first = self._crease_ends[2 * c, 0] == self.corners.vertex[p, ia]
        curve = self._crease_curve(c, np.where(first[:, None], 1.0 - t, t), Xe)
        nag = self._crease_nagata[c]
        if nag.any():
            curve[nag] = patches.evaluate(self.x[p[nag]], self.coef[p[nag]], le[nag])
        return wsum, t, curve, self.x[p, ib] - self.x[p, ia]

    @staticmethod
    def _edge_lam(t: np.ndarray, k: int) -> np.ndarray:
        """Barycentrics ``(P, k, 3)`` of the points at ``t (P, k)`` on the edge opposite corner ``k``."""
        le = np.zeros((*t.shape, 3))
        le[..., (k + 1) % 3], le[..., (k + 2) % 3] = 1.0 - t, t
        return le

    def evaluate(self, patch: npt.ArrayLike, lam: np.ndarray) -> np.ndarray:
        """Points ``(P, k, 3)`` of the fitted surface over facets ``patch (P,)`` at barycentric ``lam (P, k, nfv)``.

        On a facet with crease edges (3D) the blend is first reparametrised
        along each crease edge, so that its point on the edge lies at the same
        abscissa along the edge as the crease curve's (``lambda`` moved along
        the edge by the blend's tangential lead ``delta``, weighted by the
        edge's ``lambda_a + lambda_b``: a shift within the surface, no error);
        then the gap left between the curve and the blend's edge point, now
        across the edge only, is added with the weight ``lambda_a + lambda_b``
        (it vanishes on the other edges).  Without the shift the gap's
        tangential part, O(h^3), was carried into the facet along a fixed
        direction and tilted out of the surface by O(h): order 4 on the
        cylinder's side facets at the rims.
        """
        patch = np.asarray(patch, dtype=np.int64)
        lam = np.asarray(lam, dtype=float)
        X = np.matmul(lam, self.x[patch])
        nfv = lam.shape[2]
        edges = [np.flatnonzero(self._edge_crease[patch, k] >= 0) for k in range(3)] if nfv == 3 else []
        if not any(len(sel) for sel in edges):
            out = self._blend(patch, lam, X)
        else:
            lam2 = lam.copy()
            found = []
            for k, sel in enumerate(edges):  # the blend's lead along each crease edge over the curve
                if len(sel) == 0:
                    continue
                p = patch[sel]
                wsum, t, curve, E = self._crease_edge(p, lam[sel], k)
                le = self._edge_lam(t, k)
                Se = self._blend(p, le, np.matmul(le, self.x[p]))
                L2 = np.einsum("pi,pi->p", E, E)[:, None]
                shift = np.einsum("pki,pi->pk", Se - curve, E) / L2  # in units of t
                lam2[sel, :, (k + 1) % 3] += wsum * shift
                lam2[sel, :, (k + 2) % 3] -= wsum * shift
                found.append((k, sel, wsum, t - shift, curve))
            out = self._blend(patch, lam2, np.matmul(lam2, self.x[patch]))
            for k, sel, wsum, t2, curve in found:  # crease edges: meet the crease curve
                p = patch[sel]
                le = self._edge_lam(t2, k)
                out[sel] += wsum[..., None] * (curve - self._blend(p, le, np.matmul(le, self.x[p])))
        # bounded departure from the straight facet
        D = out - X
        bound = FIT_BOUND * np.einsum("pkv,pv->pk", lam, self._hv[self.corners.vertex[patch]])
        norm = np.linalg.norm(D, axis=2)
        over = norm > bound
        self.n_clipped = int(over.sum())
        if over.any():
            out = X + D * np.where(over, bound / np.where(over, norm, 1.0), 1.0)[..., None]
        return out

    def place(
        self, records: Records, straight: np.ndarray | None = None
    ) -> tuple[np.ndarray, Records, PlaceReport]:
        """Evaluate each facet vertex on its coarse facet's fitted surface.

        Args:
            records: records of ``nf`` facets (``params`` barycentric, ``(nf, nfv, nfv)``).
            straight: unused (placement needs no projection).

        Returns:
            ``(points (nf, nfv, 3), records, report)``.
        """
        pts = self.evaluate(records.root, records.params)
        return pts, records, PlaceReport(n_points=int(pts.shape[0] * pts.shape[1]))

    def project(self, records: Records, points: np.ndarray) -> tuple[np.ndarray, Records]:
        """Points of the fitted surface near ``points (nf, nfv, 3)``, on each slot's own coarse facet or feature.

        The barycentrics are those of the closest point on the facet's Nagata
        patch (:meth:`NagataGeometry.project
        <nagata_snap.nagata.geometry.NagataGeometry.project>`: Newton seeded by the
        records, edge and corner slots kept on their edge or vertex), evaluated
        on the fitted surface: the point returned is exactly its record's, on the
        surface, and within the two surfaces' distance of the closest point.
        """
        return super().project(records, points)
