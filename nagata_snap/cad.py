"""CAD mode: snap boundary vertices onto NURBS curves (2D) or surfaces (3D).

:class:`CadGeometry` is the snapping geometry of Kadir (2010), chapter 2:

* :meth:`CadGeometry.attach` is the initialisation of the coarse mesh
  (Kadir 2.3.1): every boundary vertex is located on the CAD geometry by a
  global search (:class:`nagata_snap.projection.GlobalSearcher`) and each
  boundary facet is assigned ONE entity (curve or surface patch) on which all
  its vertices lie (the assumption of Kadir 2.3.4).  The per-vertex
  parameters are stored per facet (Kadir 2.3.2: the ``(n, u)`` / ``(n, u, v)``
  tuples) in :class:`nagata_snap.records.Records`.
* :meth:`CadGeometry.place` is the snapping after a refinement (Kadir 2.2,
  Algorithm 1, with the neighbour-information seeds of 2.3.3): each facet
  vertex is projected by Newton (Kadir App. B, eqs. B.1/B.2) onto its facet's
  entity, seeded with the parameters carried by the records (for a new vertex,
  the parametric midpoint of its parent edge).

Parameters in closed (periodic) directions are kept *unwrapped per facet*: the
vertices of one facet never differ by a jump of a period, so parametric
midpoints are correct across seams.  Evaluation wraps them.

Example (2D, a NURBS circle and a polygon of its points)::

    >>> import numpy as np
    >>> from nagata_snap.nurbs import NurbsCurve
    >>> from nagata_snap.cad import CadGeometry
    >>> s = np.sqrt(0.5)
    >>> P = [[1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0], [-1, -1], [0, -1], [1, -1], [1, 0]]
    >>> circle = NurbsCurve(2, [0, 0, 0, .25, .25, .5, .5, .75, .75, 1, 1, 1], P,
    ...                     [1, s, 1, s, 1, s, 1, s, 1])
    >>> geo = CadGeometry([circle])
    >>> t = np.linspace(0, 2 * np.pi, 9)[:-1]
    >>> x = np.c_[np.cos(t), np.sin(t), 0 * t]
    >>> facets = np.stack([x, np.roll(x, -1, axis=0)], axis=1)   # (8, 2, 3)
    >>> rec = geo.attach(facets)
    >>> mid = facets.mean(axis=1)                                 # straight midpoints
    >>> straight = np.stack([facets[:, 0], mid], axis=1)          # first halves
    >>> rec.params = np.stack([rec.params[:, 0], rec.params.mean(axis=1)], axis=1)
    >>> pts, rec2, report = geo.place(rec, straight)
    >>> bool(np.allclose(np.linalg.norm(pts, axis=2), 1.0, atol=1e-13, rtol=0))
    True

With DOLFINx, ``facet_points`` are the coordinates of the tagged boundary
facets' vertices (``mesh.geometry.x[...]``); the lead's ``Snapper`` hook calls
``attach`` once on the coarse mesh and ``place`` after every refinement.
"""

from __future__ import annotations

import os
from typing import Sequence

import numpy as np
import numpy.typing as npt
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .nurbs import NurbsCurve, NurbsSurface
from .projection import GlobalSearcher, evaluate_params, normalize_params
from .records import Records

__all__ = ["CadError", "CadGeometry"]

#: two facet vertices closer than this (relative to the model size) are one vertex
MERGE_RTOL = 1e-10
#: a parameter direction is degenerate at a point (pole) if ``|dS/dp|`` is below
#: this fraction of the entity size (per unit parameter)
DEGENERATE_RTOL = 1e-9


class CadError(RuntimeError):
    """The mesh boundary does not match the CAD geometry (or no geometry found)."""


def _facets(a: npt.ArrayLike, what: str) -> np.ndarray:
    x = np.asarray(a, dtype=float)
    if x.ndim != 3 or x.shape[2] not in (2, 3) or x.shape[1] < 1:
        raise ValueError(f"{what} must have shape (nf, nfv, 3), got {x.shape}")
    if x.shape[2] == 2:
        x = np.concatenate([x, np.zeros(x.shape[:2] + (1,))], axis=2)
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{what} contains NaN or infinite coordinates")
    return x


def _edge_length(x: np.ndarray) -> np.ndarray:
    """Largest edge (vertex-pair distance) of each facet ``(nf, nfv, 3)`` -> ``(nf,)``."""
    nfv = x.shape[1]
    h = np.zeros(x.shape[0])
    for i in range(nfv):  # loop over facet vertices (2 or 3)
        for j in range(i + 1, nfv):
            np.maximum(h, np.linalg.norm(x[:, i] - x[:, j], axis=1), out=h)
    return h


def _groups(points: np.ndarray, radius: float, nodes: np.ndarray | None = None) -> np.ndarray:
    """Vertex id per point: equal ``nodes`` ids, else points closer than ``radius``."""
    if nodes is not None:
        return np.unique(np.asarray(nodes).reshape(-1), return_inverse=True)[1].reshape(-1)
    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    uniq, inv = np.unique(points, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    pairs = cKDTree(uniq).query_pairs(radius, output_type="ndarray")
    if len(pairs):
        m = len(uniq)
        g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
        _, lab = connected_components(g, directed=False)
        return lab[inv]
    return inv


class CadGeometry:
    """Snapping geometry from NURBS curves (2D meshes) or surfaces (3D meshes).

    Args:
        entities: the CAD entities, all :class:`~nagata_snap.nurbs.NurbsCurve`
            (2D: boundary segments are snapped to curves) or all
            :class:`~nagata_snap.nurbs.NurbsSurface` (3D: triangles to surfaces).
        tol_factor: :meth:`attach` accepts a facet if all its vertices are
            within ``tol_factor * h`` of one entity, ``h`` the facet's longest
            edge (dimensionless).
        k_seeds: nearest grid samples used as Newton seeds in global searches.
        max_iter: Newton iterations per projection in :meth:`place`.
        per_span: samples per knot span and direction of the search grid.

    Raises:
        ValueError: empty or mixed entity list.
    """

    def __init__(
        self,
        entities: Sequence[NurbsCurve] | Sequence[NurbsSurface],
        *,
        tol_factor: float = 1e-2,
        k_seeds: int = 6,
        max_iter: int = 20,
        per_span: int | None = None,
    ):
        entities = list(entities)
        if not entities:
            raise ValueError("CadGeometry needs at least one NURBS curve or surface")
        kinds = {type(e) for e in entities}
        if not (kinds <= {NurbsCurve} or kinds <= {NurbsSurface}):
            raise ValueError(
                f"entities must be all NurbsCurve or all NurbsSurface, got {sorted(k.__name__ for k in kinds)}"
            )
        self.entities = entities
        self.param_dim = entities[0].param_dim
        self.tol_factor = float(tol_factor)
        self.max_iter = int(max_iter)
        self.searcher = GlobalSearcher(entities, per_span=per_span, k_seeds=k_seeds)
        self.size = self.searcher.size
        d = self.param_dim
        self._period = np.full((len(entities), d), np.nan)
        for i, e in enumerate(entities):
            for a, closed in enumerate(e.closed):
                if closed:
                    lo, hi = e.bounds[a]
                    self._period[i, a] = hi - lo

    @classmethod
    def from_iges(
        cls, path: str | os.PathLike, *, dim: int | None = None, **kwargs
    ) -> "CadGeometry":
        """Geometry from the NURBS entities of an IGES file.

        Uses :func:`nagata_snap.iges.read_iges`, whose result has ``.curves``
        (type 126) and ``.surfaces`` (type 128).

        Args:
            path: IGES file.
            dim: mesh dimension: 2 uses the curves, 3 the surfaces; ``None``
                uses the surfaces if there are any, else the curves.
            **kwargs: passed to :class:`CadGeometry`.

        Raises:
            CadError: the file holds no entity of the kind needed.
        """
        from .iges import read_iges

        model = read_iges(path)
        curves = list(getattr(model, "curves", []) or [])
        surfaces = list(getattr(model, "surfaces", []) or [])
        if dim is None:
            ents, kind = (surfaces, "surfaces") if surfaces else (curves, "curves")
        elif dim == 2:
            ents, kind = curves, "curves"
        elif dim == 3:
            ents, kind = surfaces, "surfaces"
        else:
            raise ValueError(f"dim must be 2, 3 or None, got {dim!r}")
        if not ents:
            raise CadError(
                f"{os.fspath(path)}: no NURBS {kind} found (the file has {len(curves)} "
                f"curves and {len(surfaces)} surfaces)"
            )
        return cls(ents, **kwargs)

    # ------------------------------------------------------------------
    @property
    def num_entities(self) -> int:
        """Number of CAD entities."""
        return len(self.entities)

    def evaluate(self, root: npt.ArrayLike, params: np.ndarray) -> np.ndarray:
        """Points of records: entity ``root (nf,)`` at ``params (nf, nfv, d)`` -> ``(nf, nfv, 3)``.

        Parameters are wrapped/clamped into each entity's domain.
        """
        root = np.asarray(root, dtype=np.int64).reshape(-1)
        params = np.asarray(params, dtype=float)
        nf, nfv, d = params.shape
        out = np.empty((nf, nfv, 3))
        for e in np.unique(root):  # loop over entities
            sel = root == e
            p = normalize_params(self.entities[e], params[sel].reshape(-1, d))
            out[sel] = evaluate_params(self.entities[e], p, 0).reshape(-1, nfv, 3)
        return out

    # ------------------------------------------------------------------
    def _unwrap(self, root: np.ndarray, params: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """Shift ``params (n, d)`` by whole periods to be nearest to ``ref (n, d)``."""
        per = self._period[root]  # (n, d), nan where open
        use = ~np.isnan(per) & np.isfinite(ref)
        shift = np.round((np.where(use, ref, 0.0) - params) / np.where(use, per, 1.0))
        return params + np.where(use, shift * per, 0.0)

    def _degenerate(self, root: np.ndarray, params: np.ndarray) -> np.ndarray:
        """``(n, d)`` bool: tangent ``dS/dp_a`` vanishes (e.g. the poles of a sphere)."""
        n, d = params.shape
        out = np.zeros((n, d), dtype=bool)
        for e in np.unique(root):  # loop over entities
            sel = np.flatnonzero(root == e)
            ent = self.entities[e]
            p = normalize_params(ent, params[sel])
            _, T = evaluate_params(ent, p, 1)
            lengths = np.diff(ent.bounds, axis=1)[:, 0]  # (d,)
            thr = DEGENERATE_RTOL * ent.bbox_size / lengths
            out[sel] = np.linalg.norm(T, axis=2) <= thr[None, :]
        return out

    def _contiguous(self, root: np.ndarray, params: np.ndarray) -> np.ndarray:
        """Unwrap each facet's params across seams; fill degenerate (pole) parameters.

        ``params (nf, nfv, d)``: in each closed direction every vertex is
        shifted by whole periods towards the facet's first non-degenerate
        vertex; a parameter that is arbitrary at its vertex (a pole, where
        ``dS/dp = 0``) is replaced by the mean of the facet's other vertices,
        so that parametric midpoints of edges at the pole stay sensible.
        """
        nf, nfv, d = params.shape
        if nf == 0:
            return params
        flat_root = np.repeat(root, nfv)
        degen = self._degenerate(flat_root, params.reshape(-1, d)).reshape(nf, nfv, d)
        out = params.copy()
        rows = np.arange(nf)
        for a in range(d):  # loop over parameter directions
            good = ~degen[:, :, a]
            refslot = np.argmax(good, axis=1)  # first non-degenerate slot (0 if none)
            ref = out[rows, refslot, a]
            per = self._period[root, a]
            closed = ~np.isnan(per)
            if closed.any():
                pc = per[closed][:, None]
                col = out[closed, :, a]
                out[closed, :, a] = col + pc * np.round((ref[closed][:, None] - col) / pc)
            cnt = good.sum(axis=1)
            fix = degen[:, :, a] & (cnt > 0)[:, None]
            if fix.any():
                mean = np.where(good, out[:, :, a], 0.0).sum(axis=1) / np.maximum(cnt, 1)
                out[:, :, a] = np.where(fix, mean[:, None], out[:, :, a])
        return out

    # ------------------------------------------------------------------
    def attach(self, facet_points: npt.ArrayLike, nodes: npt.ArrayLike | None = None) -> Records:
        """Records of the coarse mesh's boundary facets (global search, Kadir 2.3.1).

        Args:
            facet_points: ``(nf, nfv, 3)`` vertex coordinates of the boundary
                facets to snap (2D: ``nfv = 2`` segments in the z = 0 plane,
                matched to curves; 3D: ``nfv = 3`` triangles, matched to surfaces).
            nodes: optional ``(nf, nfv)`` global vertex ids (vertex identity);
                by default vertices are identified by their coordinates.

        Returns:
            :class:`Records`: ``root (nf,)`` int64 entity per facet, the one
            minimising the largest vertex distance; ``params (nf, nfv, d)``
            of its vertices on it, unwrapped per facet in closed directions.

        Raises:
            CadError: a facet has a vertex farther than ``tol_factor * h`` (``h``
                its longest edge) from every entity; the message names the
                facet and the distance.
        """
        fp = _facets(facet_points, "facet_points")
        nf, nfv, _ = fp.shape
        d = self.param_dim
        ne = self.num_entities
        if nf == 0:
            return Records(np.zeros(0, dtype=np.int64), np.zeros((0, nfv, d)))
        flat = fp.reshape(-1, 3)
        gid = _groups(flat, MERGE_RTOL * self.size, nodes)
        nv = int(gid.max()) + 1
        rep = np.unique(gid, return_index=True)[1]  # first slot of each vertex
        V = flat[rep]
        h = _edge_length(fp)
        tol = self.tol_factor * h  # (nf,)

        # (vertex, entity) table: best Newton result from the KD-tree seeds
        pt, ent, par, _, dist, _ = self.searcher.search_all(V)
        keys, par_t, dist_t = self._reduce(pt * ne + ent, par, dist)  # sorted by key
        # best entity per vertex (smallest distance)
        order = np.lexsort((dist_t, keys // ne))
        first = np.searchsorted((keys // ne)[order], np.arange(nv))
        best_ent = keys[order[first]] % ne

        # candidate (facet, entity) pairs: entities within tolerance of any vertex, and
        # every vertex's best entity
        slot_v = gid.reshape(nf, nfv)
        vstart = np.searchsorted(keys, np.arange(nv) * ne)
        vend = np.searchsorted(keys, (np.arange(nv) + 1) * ne)
        cnt = (vend - vstart)[slot_v.reshape(-1)]
        rowsel = np.repeat(vstart[slot_v.reshape(-1)], cnt) + _ramp(cnt)
        fac = np.repeat(np.repeat(np.arange(nf), nfv), cnt)
        near = dist_t[rowsel] <= tol[fac]
        cf = np.concatenate([fac[near], np.repeat(np.arange(nf), nfv)])
        ce = np.concatenate([keys[rowsel][near] % ne, best_ent[slot_v.reshape(-1)]])
        pair = np.unique(cf * ne + ce)
        cf, ce = pair // ne, pair % ne

        # distance of every vertex of every candidate facet to the candidate entity
        need_v = slot_v[cf].reshape(-1)
        need_e = np.repeat(ce, nfv)
        need = need_v * ne + need_e
        pos = np.searchsorted(keys, need)
        found = (pos < len(keys)) & (keys[np.minimum(pos, len(keys) - 1)] == need)
        if not found.all():
            miss = np.unique(need[~found])
            mp, _, md = self.searcher.search_on(V[miss // ne], miss % ne)
            keys, par_t, dist_t = self._reduce(
                np.concatenate([keys, miss]), np.concatenate([par_t, mp]), np.concatenate([dist_t, md])
            )
            pos = np.searchsorted(keys, need)
        dmax = dist_t[pos].reshape(-1, nfv).max(axis=1)
        # choose per facet: smallest max distance, ties to the lowest entity index
        order = np.lexsort((ce, dmax, cf))
        first = np.searchsorted(cf[order], np.arange(nf))
        choice = order[first]
        root = ce[choice].astype(np.int64)
        score = dmax[choice]
        bad = np.flatnonzero(~(score <= tol))
        if bad.size:
            worst = bad[np.argmax(score[bad] / np.maximum(h[bad], 1e-300))]
            raise CadError(
                f"{bad.size} of {nf} boundary facets do not lie on the CAD geometry; e.g. "
                f"facet {worst} (vertices {fp[worst].round(6).tolist()}) is {score[worst]:.3e} "
                f"from the nearest entity ({root[worst]}), more than the tolerance "
                f"{tol[worst]:.3e} = tol_factor {self.tol_factor:g} x facet size {h[worst]:.3e}"
            )
        params = par_t[pos].reshape(-1, nfv, d)[choice]
        params = self._contiguous(root, params)
        return Records(root, params)

    @staticmethod
    def _reduce(key: np.ndarray, par: np.ndarray, dist: np.ndarray):
        """Keep the smallest distance per key; return rows sorted by key."""
        order = np.lexsort((dist, key))
        k = key[order]
        first = np.ones(len(k), dtype=bool)
        first[1:] = k[1:] != k[:-1]
        sel = order[first]
        return key[sel], par[sel], dist[sel]

    # ------------------------------------------------------------------
    def place(
        self, records: Records, straight: npt.ArrayLike
    ) -> tuple[np.ndarray, Records, dict]:
        """Snap facet vertices onto their facets' entities (Kadir 2.2 + 2.3.3).

        Args:
            records: ``root (nf,)`` entity per facet and ``params (nf, nfv, d)``
                seeds (old vertices: their parameters; new vertices: the
                parametric midpoint of the parent edge).
            straight: ``(nf, nfv, 3)`` current (straight) vertex positions.

        Returns:
            ``(points (nf, nfv, 3), records, report)``: projected positions
            (identical for every slot of the same vertex), records with the
            converged parameters (unwrapped relative to the seeds, hence
            contiguous within each facet), and a report with
            ``max_residual``/``mean_residual`` (snap distance ``|S(u) - P|``
            over distinct vertices, length units), ``iterations_histogram``
            (``np.bincount`` of the Newton iterations of every slot's seeded
            projection), ``n_points`` (slots), ``n_vertices``, ``n_fallback``
            (slots whose seeded Newton failed or jumped farther than the
            facet's longest edge), ``n_off_root`` (positions taken from
            another entity) and ``n_unresolved`` (no acceptable projection
            found; the closest point found is used).

        Fallbacks, in order: the other vertices' parameters of the facet and
        their mean as seeds; KD-tree seeds on the facet's entity and on
        entities whose bounding box is within an edge length; a global search.
        """
        st = _facets(straight, "straight")
        root = np.asarray(records.root, dtype=np.int64).reshape(-1)
        params = np.asarray(records.params, dtype=float)
        nf, nfv, _ = st.shape
        d = self.param_dim
        if root.shape != (nf,) or params.shape != (nf, nfv, d):
            raise ValueError(
                f"records (root {root.shape}, params {params.shape}) do not match "
                f"straight {st.shape} (expected root ({nf},), params ({nf}, {nfv}, {d}))"
            )
        if nf and (root.min() < 0 or root.max() >= self.num_entities):
            raise ValueError(f"records.root refers to entities outside 0..{self.num_entities - 1}")
        ns = nf * nfv
        if ns == 0:
            report = {
                "max_residual": 0.0, "mean_residual": 0.0,
                "iterations_histogram": np.zeros(1, dtype=np.int64), "n_points": 0,
                "n_vertices": 0, "n_fallback": 0, "n_off_root": 0, "n_unresolved": 0,
            }
            return np.zeros((nf, nfv, 3)), Records(root.copy(), params.copy()), report
        X = st.reshape(ns, 3)
        ent = np.repeat(root, nfv)
        seed = params.reshape(ns, d)
        hs = np.repeat(_edge_length(st), nfv)
        big = np.finfo(float).max

        # 1. seeded Newton on the facet's entity
        par, proj, dist, its, conv = self.searcher.refine(np.arange(ns), ent, seed, X, self.max_iter)
        valid = conv & (dist <= hs) & np.all(np.isfinite(proj), axis=1)
        dist = np.where(np.isfinite(dist), dist, big)
        on_root = np.ones(ns, dtype=bool)
        bad = np.flatnonzero(~valid)
        n_fallback = int(bad.size)

        if bad.size:
            # 2. other seeds: the facet's other vertices' params and their mean
            f = bad // nfv
            cand = np.concatenate([params[f], params[f].mean(axis=1, keepdims=True)], axis=1)
            m = nfv + 1
            pt = np.repeat(bad, m)
            cp, cx, cd, _, cc = self.searcher.refine(pt, ent[pt], cand.reshape(-1, d), X, self.max_iter)
            ok = cc & (cd <= hs[pt])
            rows = _best_rows(np.repeat(np.arange(bad.size), m), cd, ok, bad.size)
            hit = rows >= 0
            s, r = bad[hit], rows[hit]
            par[s], proj[s], dist[s], valid[s] = cp[r], cx[r], cd[r], True
            bad = np.flatnonzero(~valid)
        if bad.size:
            # 3. KD-tree seeds on the root entity and on entities whose bbox is near
            lo, hi = self.searcher.bbox_lo, self.searcher.bbox_hi
            Xb, hb = X[bad], hs[bad]
            near = np.all(
                (Xb[:, None, :] >= lo[None] - hb[:, None, None])
                & (Xb[:, None, :] <= hi[None] + hb[:, None, None]),
                axis=2,
            )  # (nb, ne)
            near[np.arange(bad.size), ent[bad]] = True
            bi, be = np.nonzero(near)
            qp, qx, qd = self.searcher.search_on(Xb[bi], be)
            qroot = be == ent[bad][bi]
            qok = qd <= hb[bi]
            r_root = _best_rows(bi, qd, qroot, bad.size)  # best attempt on the root
            r_ok = _best_rows(bi, qd, qok & qroot, bad.size)  # acceptable on the root
            r_any = _best_rows(bi, qd, qok, bad.size)  # acceptable anywhere
            use_root = r_ok >= 0
            use_other = ~use_root & (r_any >= 0)
            s, r = bad[use_root], r_ok[use_root]
            par[s], proj[s], dist[s], valid[s] = qp[r], qx[r], qd[r], True
            s, r = bad[use_other], r_any[use_other]
            proj[s], dist[s], valid[s], on_root[s] = qx[r], qd[r], True, False
            # root parameters of the off-root or still-bad slots: the best root attempt
            upd = ~use_root & (r_root >= 0)
            s, r = bad[upd], r_root[upd]
            closer = ~valid[s] & (qd[r] < dist[s])
            par[s] = np.where((~valid[s] | ~on_root[s])[:, None], qp[r], par[s])
            proj[s[closer]], dist[s[closer]] = qx[r[closer]], qd[r[closer]]
            bad = np.flatnonzero(~valid)
        if bad.size:
            # 4. global search over all entities
            ge, gp, gd = self.searcher.search(X[bad])
            gx = np.empty((bad.size, 3))
            for e in np.unique(ge):  # loop over entities
                s = ge == e
                gx[s] = evaluate_params(self.entities[e], normalize_params(self.entities[e], gp[s]), 0)
            groot = ge == ent[bad]
            take = (gd <= hs[bad]) | (gd < dist[bad])
            s = bad[take]
            proj[s], dist[s], on_root[s] = gx[take], gd[take], groot[take]
            valid[s] = gd[take] <= hs[s]
            sr = take & groot
            par[bad[sr]] = gp[sr]
        n_unresolved = int(np.sum(~valid))

        # params: unwrap relative to the seeds (contiguous within the facet);
        # facets with non-finite seeds relative to their first vertex
        par = self._unwrap(ent, par, seed)
        nanf = ~np.all(np.isfinite(seed).reshape(nf, -1), axis=1)
        if nanf.any():
            pf = par.reshape(nf, nfv, d)
            sub = pf[nanf]
            ref = np.repeat(sub[:, :1], nfv, axis=1).reshape(-1, d)
            pf[nanf] = self._unwrap(np.repeat(root[nanf], nfv), sub.reshape(-1, d), ref).reshape(-1, nfv, d)
            par = pf.reshape(ns, d)
        # one position per mesh vertex: the best slot's
        gid = _groups(X, MERGE_RTOL * self.size)
        order = np.lexsort((dist, ~on_root, ~valid, gid))
        g_sorted = gid[order]
        first = np.ones(ns, dtype=bool)
        first[1:] = g_sorted[1:] != g_sorted[:-1]
        rep_of_group = np.empty(int(gid.max()) + 1 if ns else 0, dtype=np.int64)
        rep_of_group[g_sorted[first]] = order[first]
        rep = rep_of_group[gid]
        # same entity but a different position than the representative: take its params
        off = (ent == ent[rep]) & (np.linalg.norm(proj - proj[rep], axis=1) > 1e-9 * self.size)
        if off.any():
            par[off] = self._unwrap(ent[off], par[rep[off]], seed[off])
        proj = proj[rep]
        dist = np.linalg.norm(proj - X, axis=1)
        vd = dist[rep_of_group]  # one value per distinct vertex

        report = {
            "max_residual": float(vd.max()) if vd.size else 0.0,
            "mean_residual": float(vd.mean()) if vd.size else 0.0,
            "iterations_histogram": np.bincount(its, minlength=1),
            "n_points": int(ns),
            "n_vertices": int(vd.size),
            "n_fallback": n_fallback,
            "n_off_root": int(np.sum(~on_root)),
            "n_unresolved": n_unresolved,
        }
        return proj.reshape(nf, nfv, 3), Records(root.copy(), par.reshape(nf, nfv, d)), report


def _best_rows(group: np.ndarray, score: np.ndarray, mask: np.ndarray, n: int) -> np.ndarray:
    """Per group ``0..n-1``: row with the smallest ``score`` among ``mask``, or -1."""
    out = np.full(n, -1, dtype=np.int64)
    rows = np.flatnonzero(mask)
    if rows.size:
        order = rows[np.lexsort((score[rows], group[rows]))]
        g, first = np.unique(group[order], return_index=True)
        out[g] = order[first]
    return out


def _ramp(counts: np.ndarray) -> np.ndarray:
    """``[0..c0-1, 0..c1-1, ...]`` for counts ``c`` (vectorised)."""
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    starts = np.cumsum(counts) - counts
    return np.arange(total) - np.repeat(starts, counts)
