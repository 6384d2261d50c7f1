"""IGES (fixed-format ASCII) writer for NURBS curves and surfaces.

Reading CAD files (IGES, STEP, BREP) is OpenCASCADE's job
(:mod:`nagata_snap.cad.read`); this module writes NURBS entities as IGES 5.3
for tests and demos: entity 126 (rational B-spline curve, form 0) and 128
(rational B-spline surface, form 0), Kadir (2010), Appendix C.

File layout (IGES 5.3, sec. 2): 80-column records, the section letter in
column 73 (``S`` start, ``G`` global, ``D`` directory, ``P`` parameter data,
``T`` terminate) and the sequence number in columns 74-80.  The Global
section (columns 1-72) starts with the parameter and record delimiters as
Hollerith strings (``1H,`` and ``1H;``).  A directory entry is a pair of
``D`` lines of ten 8-column fields; parameter data lines hold data in
columns 1-64 and the DE back-pointer in columns 66-72.  The terminate
record gives the line counts of the S, G, D and P sections.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from nagata_snap.cad.nurbs import NurbsCurve, NurbsSurface

__all__ = ["write_iges", "format_iges", "UNIT_FLAGS"]

#: IGES 5.3 Global parameter 14 (unit flag) -> unit name (Global parameter 15).
UNIT_FLAGS: dict[int, str] = {
    1: "INCH", 2: "MM", 4: "FT", 5: "MI", 6: "M", 7: "KM",
    8: "MIL", 9: "UM", 10: "CM", 11: "UIN",
}
_UNIT_NAMES = {v: k for k, v in UNIT_FLAGS.items()}
_UNIT_NAMES.update({"IN": 1, "MICRON": 9, "METER": 6, "METRE": 6, "MILLIMETER": 2})


def _is_clamped(p: int, U: np.ndarray, n: int) -> bool:
    return bool(np.all(U[: p + 1] == U[p]) and np.all(U[n:] == U[n]))


# ======================================================================
# writer
# ======================================================================
def _fmt_real(x: float) -> str:
    """Shortest round-trip decimal with a decimal point and an ``E`` exponent."""
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"cannot write the non-finite value {x!r} to IGES")
    s = repr(x)
    if "e" in s:
        mant, ex = s.split("e")
        if "." not in mant:
            mant += ".0"
        return f"{mant}E{ex}"
    if "." not in s:
        s += ".0"
    return s


def _holl(s: str) -> str:
    return f"{len(s)}H{s}"


def _pack(tokens: Sequence[str], width: int, pd: str = ",", rd: str = ";") -> list[str]:
    """Pack tokens, each followed by its delimiter, into lines of at most ``width``."""
    lines, cur = [], ""
    for k, t in enumerate(tokens):
        item = t + (rd if k == len(tokens) - 1 else pd)
        if len(item) > width:
            raise ValueError(f"IGES token too long for one line: {item[:40]}...")
        if len(cur) + len(item) > width:
            lines.append(cur)
            cur = ""
        cur += item
    if cur:
        lines.append(cur)
    return lines


def _planar_normal(P: np.ndarray) -> np.ndarray | None:
    Q = P - P.mean(axis=0)
    size = float(np.linalg.norm(P.max(0) - P.min(0)))
    if size == 0:
        return None
    _, sv, vt = np.linalg.svd(Q, full_matrices=True)
    sv = np.concatenate([sv, np.zeros(3 - len(sv))])
    if sv[2] <= 1e-12 * size * max(1.0, math.sqrt(len(P))):
        n = vt[2]
        k = int(np.argmax(np.abs(n)))
        return n if n[k] > 0 else -n
    return None


def _close(a: np.ndarray, b: np.ndarray, size: float) -> bool:
    return bool(np.all(np.linalg.norm(a - b, axis=-1) <= 1e-9 * max(size, 1e-300)))


def _curve_params(c: NurbsCurve) -> list[str]:
    P = np.asarray(c.control_points, float)
    W = np.asarray(c.weights, float)
    U = np.asarray(c.knots, float)
    p = int(c.degree)
    n = P.shape[0]
    size = float(np.linalg.norm(P.max(0) - P.min(0)))
    nrm = _planar_normal(P)
    ends = c.evaluate(np.array([U[p], U[n]]))[0]
    closed = _close(ends[0], ends[1], size)
    poly = bool(np.all(W[0] == W))
    toks = ["126", str(n - 1), str(p), "1" if nrm is not None else "0", "1" if closed else "0",
            "1" if poly else "0", "0"]
    toks += [_fmt_real(x) for x in U]
    toks += [_fmt_real(x) for x in W]
    toks += [_fmt_real(x) for x in P.ravel()]
    toks += [_fmt_real(float(U[p])), _fmt_real(float(U[n]))]
    toks += [_fmt_real(x) for x in (nrm if nrm is not None else np.zeros(3))]
    return toks


def _surface_params(s: NurbsSurface) -> list[str]:
    P = np.asarray(s.control_points, float)
    W = np.asarray(s.weights, float)
    U = np.asarray(s.knots_u, float)
    V = np.asarray(s.knots_v, float)
    p, q = int(s.degree_u), int(s.degree_v)
    nu, nv = W.shape
    size = float(np.linalg.norm(P.reshape(-1, 3).max(0) - P.reshape(-1, 3).min(0)))
    cu = _close(P[0], P[-1], size) and _is_clamped(p, U, nu)
    cv = _close(P[:, 0], P[:, -1], size) and _is_clamped(q, V, nv)
    poly = bool(np.all(W.flat[0] == W))
    toks = ["128", str(nu - 1), str(nv - 1), str(p), str(q), "1" if cu else "0", "1" if cv else "0",
            "1" if poly else "0", "0", "0"]
    toks += [_fmt_real(x) for x in U]
    toks += [_fmt_real(x) for x in V]
    toks += [_fmt_real(x) for x in W.T.ravel()]  # W(i,j), i (u) fastest
    toks += [_fmt_real(x) for x in P.transpose(1, 0, 2).ravel()]
    toks += [_fmt_real(float(x)) for x in (U[p], U[nu], V[q], V[nv])]
    return toks


def format_iges(
    entities: Sequence[tuple[int, int, Sequence[str]]],
    *,
    start: Sequence[str] = ("nagata_snap IGES export",),
    global_params: Sequence[str] | None = None,
    filename: str = "nagata_snap.igs",
    author: str = "nagata_snap",
    units: str = "MM",
    timestamp: str = "20000101.000000",
    max_coord: float = 1.0,
) -> str:
    """Lay out a fixed-format IGES file from raw entity parameter tokens.

    Args:
        entities: ``(entity type, form, tokens[, transform DE[, status]])``
            with ``tokens[0]`` the entity type; tokens are written as given
            (numbers as strings).  The entity at index ``i`` gets DE number
            ``2 i + 1``; ``transform`` (default 0) fills DE field 7 and
            ``status`` (8 digits, default ``00000000``) DE field 9.
        start: Start-section lines (at most 72 characters each).
        global_params: Global parameters 3.. as ready tokens (default: a
            complete IGES 5.3 set built from the keyword arguments).

    Returns:
        The file text, 80-column lines joined by ``\\n`` with a final newline.
    """
    units_u = units.strip().upper()
    flag = _UNIT_NAMES.get(units_u, 3)
    if global_params is None:
        res = max(1e-7 * max_coord, 1e-12)
        global_params = [
            _holl("nagata_snap"), _holl(filename[-60:]), _holl("nagata_snap"), _holl("nagata_snap iges.py"),
            "32", "38", "6", "308", "15", _holl("nagata_snap"), "1.0", str(flag), _holl(units_u),
            "1", "0.01", _holl(timestamp), _fmt_real(res), _fmt_real(max_coord), _holl(author[:60]),
            _holl(""), "11", "0", _holl(timestamp),
        ]
    out = []
    s_lines = [s[:72] for s in start] or [""]
    for k, s in enumerate(s_lines, 1):
        out.append(f"{s:<72s}S{k:07d}")
    g_lines = _pack(["1H,", "1H;", *list(global_params)], 72)
    for k, s in enumerate(g_lines, 1):
        out.append(f"{s:<72s}G{k:07d}")
    d_lines: list[str] = []
    p_lines: list[str] = []
    for idx, ent in enumerate(entities):
        etype, form, toks = ent[0], ent[1], ent[2]
        trans = ent[3] if len(ent) > 3 else 0
        st = ent[4] if len(ent) > 4 else "00000000"
        de = 2 * idx + 1
        lines = _pack(list(toks), 64)
        ptr = len(p_lines) + 1
        for s in lines:
            p_lines.append(f"{s:<64s} {de:7d}P{len(p_lines) + 1:07d}")
        d_lines.append(f"{etype:8d}{ptr:8d}{0:8d}{0:8d}{0:8d}{0:8d}{trans:8d}{0:8d}{st:8s}D{de:07d}")
        d_lines.append(f"{etype:8d}{0:8d}{0:8d}{len(lines):8d}{form:8d}{'':8s}{'':8s}{'':8s}{0:8d}D{de + 1:07d}")
    out += d_lines + p_lines
    out.append(f"S{len(s_lines):7d}G{len(g_lines):7d}D{len(d_lines):7d}P{len(p_lines):7d}".ljust(72) + "T0000001")
    assert all(len(s) == 80 for s in out)
    return "\n".join(out) + "\n"


def write_iges(
    path: str | os.PathLike,
    curves: Iterable[NurbsCurve] = (),
    surfaces: Iterable[NurbsSurface] = (),
    *,
    author: str = "nagata_snap",
    units: str = "MM",
    timestamp: str = "20000101.000000",
    description: str = "nagata_snap IGES export",
) -> None:
    """Write NURBS curves (entity 126, form 0) and surfaces (128, form 0) as IGES 5.3.

    All lines are exactly 80 columns; numbers are written with the shortest
    decimal that reads back to the same double (``repr``), so a write/read
    round trip reproduces knots, weights and control points exactly.  The
    parameter range written is the knot domain.  The file is deterministic
    (fixed ``timestamp`` unless given).

    Args:
        path: output file.
        curves: :class:`NurbsCurve` objects (``(n,3)`` control points).
        surfaces: :class:`NurbsSurface` objects (``(nu,nv,3)`` nets).
        author: Global parameter 21.
        units: unit name (``'MM'``, ``'M'``, ``'INCH'``, ...; Global 14/15).
        timestamp: ``YYYYMMDD.HHNNSS`` for Global parameters 18 and 25.
        description: Start-section text.
    """
    curves, surfaces = list(curves), list(surfaces)
    if not curves and not surfaces:
        raise ValueError("write_iges: nothing to write (no curves and no surfaces)")
    ents = [(126, 0, _curve_params(c)) for c in curves] + [(128, 0, _surface_params(s)) for s in surfaces]
    allp = [np.asarray(c.control_points).reshape(-1, 3) for c in curves] + [
        np.asarray(s.control_points).reshape(-1, 3) for s in surfaces]
    mc = float(max(np.abs(a).max() for a in allp)) or 1.0
    start = [description[i:i + 72] for i in range(0, max(len(description), 1), 72)]
    text = format_iges(ents, start=start, filename=Path(path).name, author=author, units=units,
                       timestamp=timestamp, max_coord=mc)
    Path(path).write_text(text, encoding="ascii", newline="\n")
