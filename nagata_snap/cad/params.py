"""Parameters of facet vertices on their entities: seams, poles and normals.

Parameters in closed (periodic) directions are kept *unwrapped per facet*:
the vertices of one facet never differ by a jump of a period, so parametric
midpoints are correct across seams (:func:`contiguous`, :func:`unwrap`);
evaluation wraps them.  At a degenerate point (a pole of a sphere, the apex
of a cone, a collapsed NURBS edge, where ``dS/dp_a = 0``) parameter ``a`` is
arbitrary: :func:`contiguous` replaces it by the mean of the facet's other
vertices, and :func:`unit_normals` is zero there.

``entities`` are the geometry's curves or surfaces
(:mod:`nagata_snap.cad.nurbs`, :mod:`nagata_snap.cad.curves`,
:mod:`nagata_snap.cad.surfaces`), ``periods (n_entities, d)`` their periods
(NaN where open, :func:`nagata_snap.cad.projection.entity_periods`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from nagata_snap.cad.projection import evaluate_params, normalize_params
from nagata_snap.mesh.arrays import Groups

__all__ = ["DEGENERATE_RTOL", "unwrap", "degenerate", "contiguous", "unit_normals"]

#: a parameter direction is degenerate at a point (pole) if ``|dS/dp|`` is below
#: this fraction of the entity size (per unit parameter)
DEGENERATE_RTOL = 1e-9


def unwrap(periods: np.ndarray, root: np.ndarray, params: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Shift ``params (n, d)`` on entities ``root (n,)`` by whole periods to be nearest to ``ref (n, d)``."""
    per = periods[root]  # (n, d), nan where open
    use = np.isfinite(per) & np.isfinite(ref)
    shift = np.round((np.where(use, ref, 0.0) - params) / np.where(use, per, 1.0))
    return params + np.where(use, shift * per, 0.0)


def degenerate(entities: Sequence[Any], root: np.ndarray, params: np.ndarray) -> np.ndarray:
    """``(n, d)`` bool: tangent ``dS/dp_a`` at ``params (n, d)`` of ``root (n,)`` vanishes (e.g. a pole)."""
    n, d = params.shape
    out = np.zeros((n, d), dtype=bool)
    can = np.array([getattr(e, "can_degenerate", True) for e in entities])  # pole, apex, collapsed edge
    rows = can[root].nonzero()[0]
    if not rows.size:
        return out
    g = Groups(root[rows])
    P = params[rows[g.order]]
    found = np.zeros((len(rows), d), dtype=bool)
    for e, sl in g:  # loop over entities that have degenerate points
        ent = entities[e]
        _, T = evaluate_params(ent, normalize_params(ent, P[sl]), 1)
        lengths = np.diff(ent.bounds, axis=1)[:, 0]  # (d,)
        thr = DEGENERATE_RTOL * ent.bbox_size / np.maximum(lengths, 1e-300)
        found[sl] = np.linalg.norm(T, axis=2) <= thr[None, :]
    out[rows] = g.unsort(found)
    return out


def contiguous(entities: Sequence[Any], periods: np.ndarray, root: np.ndarray, params: np.ndarray) -> np.ndarray:
    """Unwrap each facet's params across seams; fill degenerate (pole) parameters.

    ``root (nf,)``, ``params (nf, nfv, d)``: in each closed direction every
    vertex is shifted by whole periods towards the facet's first
    non-degenerate vertex; a parameter that is arbitrary at its vertex (a
    pole) is replaced by the mean of the facet's other vertices, so that
    parametric midpoints of edges at the pole stay sensible.
    """
    nf, nfv, d = params.shape
    if nf == 0:
        return params
    degen = degenerate(entities, np.repeat(root, nfv), params.reshape(-1, d)).reshape(nf, nfv, d)
    if not (degen.any() or np.isfinite(periods[root]).any()):
        return params.copy()  # no seam, no pole
    good = ~degen
    refslot = np.argmax(good, axis=1)  # (nf, d): first non-degenerate slot per direction (0 if none)
    ref = np.take_along_axis(params, refslot[:, None, :], axis=1)[:, 0]
    out = unwrap(periods, np.repeat(root, nfv), params.reshape(-1, d),
                 np.repeat(ref, nfv, axis=0)).reshape(nf, nfv, d)
    cnt = good.sum(axis=1)  # (nf, d)
    fix = degen & (cnt > 0)[:, None, :]
    if fix.any():
        mean = np.where(good, out, 0.0).sum(axis=1) / np.maximum(cnt, 1)
        out = np.where(fix, mean[:, None, :], out)
    return out


def unit_normals(entities: Sequence[Any], ent: np.ndarray, params: np.ndarray) -> np.ndarray:
    """``(n, 3)`` unit ``S_u x S_v`` at ``params (n, 2)`` of surfaces ``ent (n,)``; zero where
    degenerate and on curves."""
    out = np.zeros((len(ent), 3))
    g = Groups(ent)
    for e, sl in g:  # loop over entities
        ent_e = entities[e]
        if ent_e.param_dim != 2:
            continue
        sel = g.order[sl]
        _, T = evaluate_params(ent_e, normalize_params(ent_e, params[sel]), 1)
        c = np.cross(T[:, 0], T[:, 1])
        n = np.linalg.norm(c, axis=1)
        lengths = np.diff(ent_e.bounds, axis=1)[:, 0]
        ok = n > (DEGENERATE_RTOL * ent_e.bbox_size) ** 2 / np.maximum(lengths[0] * lengths[1], 1e-300)
        out[sel[ok]] = c[ok] / n[ok, None]
    return out
