"""IGES (fixed-format ASCII) reader and writer for NURBS curves and surfaces.

Source documents: Kadir (2010), Appendix C (seed 003: file layout, entities
126 and 128, the two printed example files) and Appendix A of Neto (seed 000,
an IGES file written by GiD); the fixed format itself follows IGES 5.3
(US PRO 1996).

File layout (IGES 5.3, sec. 2): 80-column records, the section letter in
column 73 (``S`` start, ``G`` global, ``D`` directory, ``P`` parameter data,
``T`` terminate) and the sequence number in columns 74-80.  The Global
section (columns 1-72, concatenated) starts with the parameter and record
delimiters as Hollerith strings (``1H,`` and ``1H;``, defaults ``,`` ``;``).
A directory entry is a pair of ``D`` lines of ten 8-column fields (entity
type, parameter data pointer, structure, line font, level, view,
transformation matrix pointer (field 7), label display, status number
(field 9, four 2-digit flags: blank, subordinate, entity use, hierarchy);
entity type, line weight, colour, parameter line count (field 14), form
number (field 15), ...).  Parameter data lines hold data in columns 1-64 and
the DE back-pointer in columns 66-72.  The terminate record gives the line
counts of the S, G, D and P sections.

Entities read (IGES 5.3 chapter 4):

* 126 rational B-spline curve, forms 0-5 (Kadir C.2.1) and 128 rational
  B-spline surface, forms 0-9 (Kadir C.2.2): taken as they are (the form is
  informational).  A parameter range ``V(0), V(1)`` (``U(0..1), V(0..1)``)
  that is a proper sub-range of the knot domain trims the entity (exact knot
  insertion); a range that does not fit the knot vector (Kadir's printed
  cylinder writes ``0,0,0,0``) is replaced by the knot domain with a warning.
* 100 circular arc -> exact rational quadratic NURBS (at most 90 degrees per
  segment, knots at the arc angles); 110 line -> degree 1; 102 composite
  curve -> one NURBS (segments degree-elevated and joined; split where
  segments do not meet); 120 surface of revolution -> exact rational NURBS
  (generatrix x revolved arc), parameters ``(t, theta)``; 122 tabulated
  cylinder -> directrix x degree 1; 108 plane -> bilinear patch spanning
  the bounding curve (bounded form, or the boundary of a 144 over it);
  124 transformation matrix -> applied to every entity whose DE field 7
  points to it (chains composed); 142 curve on a parametric surface and 144
  trimmed surface -> underlying surface plus the outer (and inner) trimming
  loops as polygons in the NURBS parameter space.
* Everything else is skipped with one :class:`IgesWarning` per entity type.

Entities only referenced by others (segments of a 102, the generatrix of a
120, the curves and surface of a 142/144, param-space curves with entity use
flag 05, physically dependent curves) are not reported on their own.
"""

from __future__ import annotations

import math
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, NamedTuple, Sequence

import numpy as np

from .nurbs import NurbsCurve, NurbsError, NurbsSurface

__all__ = [
    "IgesError",
    "IgesWarning",
    "IgesModel",
    "read_iges",
    "write_iges",
    "points_in_polygon",
    "format_iges",
    "UNIT_FLAGS",
]


class IgesError(ValueError):
    """Malformed or unusable IGES data; the message says what and where."""


class IgesWarning(UserWarning):
    """Recoverable problem in an IGES file (skipped entities, odd ranges, ...)."""


#: IGES 5.3 Global parameter 14 (unit flag) -> unit name (Global parameter 15).
UNIT_FLAGS: dict[int, str] = {
    1: "INCH", 2: "MM", 4: "FT", 5: "MI", 6: "M", 7: "KM",
    8: "MIL", 9: "UM", 10: "CM", 11: "UIN",
}
_UNIT_NAMES = {v: k for k, v in UNIT_FLAGS.items()}
_UNIT_NAMES.update({"IN": 1, "MICRON": 9, "METER": 6, "METRE": 6, "MILLIMETER": 2})

#: if True, unexpected Python exceptions inside :func:`read_iges` are turned
#: into :class:`IgesError` (a safety net for malformed files).  Tests switch it
#: off to find reader bugs.
_WRAP_INTERNAL_ERRORS = True

_CURVE_TYPES = (100, 102, 110, 126)
_SURFACE_TYPES = (108, 120, 122, 128, 144)
_SUPPORTED = {100, 102, 108, 110, 120, 122, 124, 126, 128, 142, 144}
_MAX_DEPTH = 64
_TWO_PI = 2.0 * math.pi

_NUM_RE = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[EeDd][+-]?\d+)?")
_INT_RE = re.compile(r"[+-]?\d+")
_HOLL_RE = re.compile(r"\s*(\d+)[Hh]")


# ======================================================================
# public data
# ======================================================================
@dataclass
class IgesModel:
    """Geometry read from an IGES file.

    Attributes:
        curves: top-level curves (126, 100, 110, 102, model-space 142), as NURBS.
        surfaces: top-level surfaces (128, 120, 122, bounded 108, 144), as NURBS.
        trim_loops: one entry per surface: the outer trimming loop as a
            ``(k, 2)`` polygon in the surface's ``(u, v)`` NURBS parameters
            (implicitly closed, the first vertex is not repeated), or ``None``
            when the whole surface is the face.
        skipped: entity type -> number of entities not converted.
        units: unit name from the Global section (parameter 15, else derived
            from the unit flag, parameter 14; IGES default ``'INCH'``).
        source: file name (``'<text>'`` when read from a string).
        unit_flag: Global parameter 14 (1 inch, 2 mm, 6 m, ...).
        trim_holes: per surface, the inner trimming loops (144 ``PTI``) as
            ``(k, 2)`` polygons, possibly empty.
        curve_de, surface_de: directory entry numbers the curves / surfaces
            came from (for messages).
    """

    curves: list[NurbsCurve] = field(default_factory=list)
    surfaces: list[NurbsSurface] = field(default_factory=list)
    trim_loops: list[np.ndarray | None] = field(default_factory=list)
    skipped: dict[int, int] = field(default_factory=dict)
    units: str = "INCH"
    source: str = "<text>"
    unit_flag: int = 1
    trim_holes: list[list[np.ndarray]] = field(default_factory=list)
    curve_de: list[int] = field(default_factory=list)
    surface_de: list[int] = field(default_factory=list)


def points_in_polygon(polygon: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Even-odd point-in-polygon test, vectorised over points.

    Args:
        polygon: ``(k, 2)`` vertices (implicitly closed).
        pts: ``(m, 2)`` query points.

    Returns:
        ``(m,)`` bool, True inside.
    """
    poly = np.asarray(polygon, dtype=float)
    pts = np.atleast_2d(np.asarray(pts, dtype=float))
    a = poly
    b = np.roll(poly, -1, axis=0)
    x, y = pts[:, 0:1], pts[:, 1:2]  # (m,1)
    ay, by = a[None, :, 1], b[None, :, 1]
    crosses = (ay > y) != (by > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xint = a[None, :, 0] + (y - ay) * (b[None, :, 0] - a[None, :, 0]) / (by - ay)
    hit = crosses & (x < xint)
    return (np.count_nonzero(hit, axis=1) % 2) == 1


# ======================================================================
# homogeneous NURBS array helpers (knot insertion, restriction, elevation)
# ======================================================================
class _C(NamedTuple):
    """Internal curve: degree, knots (m,), homogeneous control points (n, 4).

    ``pmap`` maps the entity's IGES parameter to the NURBS parameter (None:
    identity); used for parameter-space trimming curves.
    """

    p: int
    U: np.ndarray
    Pw: np.ndarray
    pmap: Callable[[np.ndarray], np.ndarray] | None = None
    exact: tuple | None = None  # (P, W) as read, while Pw is unchanged


class _S(NamedTuple):
    """Internal surface: degrees, knots, homogeneous net (nu, nv, 4), param map."""

    p: int
    q: int
    U: np.ndarray
    V: np.ndarray
    Pw: np.ndarray
    pmap: Callable[[np.ndarray], np.ndarray] | None = None
    exact: tuple | None = None  # (P, W) as read, while Pw is unchanged


def _homog(P: np.ndarray, W: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore", invalid="ignore"):
        return np.concatenate([P * W[..., None], W[..., None]], axis=-1)


def _cart(Pw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return Pw[..., :3] / Pw[..., 3:], Pw[..., 3].copy()


def _mult(U: np.ndarray, u: float) -> int:
    return int(np.count_nonzero(U == u))


def _insert_knot(p: int, U: np.ndarray, Pw: np.ndarray, u: float) -> tuple[np.ndarray, np.ndarray]:
    """Insert ``u`` once (Boehm; Piegl & Tiller A5.1) along axis 0 of ``Pw``."""
    n = Pw.shape[0]
    k = int(np.searchsorted(U, u, side="right")) - 1
    s = _mult(U, u)
    lo, hi = k - p + 1, k - s
    Q = np.empty((n + 1,) + Pw.shape[1:])
    Q[:lo] = Pw[:lo]
    Q[hi + 1:] = Pw[hi:]
    if hi >= lo:
        i = np.arange(lo, hi + 1)
        a = ((u - U[i]) / (U[i + p] - U[i])).reshape((-1,) + (1,) * (Pw.ndim - 1))
        Q[lo:hi + 1] = a * Pw[lo:hi + 1] + (1.0 - a) * Pw[lo - 1:hi]
    return np.insert(U, k + 1, u), Q


def _restrict(p: int, U: np.ndarray, Pw: np.ndarray, a: float, b: float) -> tuple[np.ndarray, np.ndarray]:
    """Clamped representation of the part over ``[a, b]`` (inside the domain), axis 0."""
    for x in (a, b):
        for _ in range(max(0, p - _mult(U, x))):
            U, Pw = _insert_knot(p, U, Pw, x)
    i1 = int(np.searchsorted(U, a, side="right")) - 1
    j0 = int(np.searchsorted(U, b, side="left"))
    U2 = np.concatenate([np.full(p + 1, a), U[i1 + 1:j0], np.full(p + 1, b)])
    return U2, Pw[i1 - p:j0].copy()


def _domain(p: int, U: np.ndarray, n: int) -> tuple[float, float]:
    return float(U[p]), float(U[n])


def _is_clamped(p: int, U: np.ndarray, n: int) -> bool:
    return bool(np.all(U[:p + 1] == U[p]) and np.all(U[n:] == U[n]))


def _clamp_curve(c: _C) -> _C:
    n = c.Pw.shape[0]
    if _is_clamped(c.p, c.U, n):
        return c
    a, b = _domain(c.p, c.U, n)
    U, Pw = _restrict(c.p, c.U, c.Pw, a, b)
    return _C(c.p, U, Pw, c.pmap)


def _elevate(c: _C, t: int) -> _C:
    """Raise the degree of a clamped curve by ``t`` (Bezier decomposition)."""
    if t <= 0:
        return c
    p, U, Pw = c.p, c.U, c.Pw
    a, b = U[0], U[-1]
    inner = np.unique(U[(U > a) & (U < b)])
    for x in inner:
        m = _mult(U, x)
        if m > p:
            raise _Unsupported("discontinuous B-spline segment cannot be degree-elevated")
        for _ in range(p - m):
            U, Pw = _insert_knot(p, U, Pw, x)
    nseg = len(inner) + 1
    B = np.stack([Pw[s * p:s * p + p + 1] for s in range(nseg)])  # (nseg, p+1, 4)
    ph = p + t
    E = np.zeros((ph + 1, p + 1))
    for i in range(ph + 1):
        for j in range(max(0, i - t), min(p, i) + 1):
            E[i, j] = math.comb(p, j) * math.comb(t, i - j) / math.comb(ph, i)
    Bh = np.einsum("ij,sjc->sic", E, B)
    Q = np.concatenate([Bh[0]] + [Bh[s][1:] for s in range(1, nseg)])
    U2 = np.concatenate([np.full(ph + 1, a)] + [np.full(ph, x) for x in inner] + [np.full(ph + 1, b)])
    return _C(ph, U2, Q, c.pmap)


def _arc(center: np.ndarray, X: np.ndarray, Y: np.ndarray, th0: float, th1: float) -> tuple:
    """Rational quadratic arc ``center + cos(a) X + sin(a) Y``, ``a`` in ``[th0, th1]``.

    Piegl & Tiller (1997) A7.1 with at most 90 degrees per segment; the knots
    are the segment end angles, so the NURBS parameter equals the angle at the
    knots.  Returns ``(U (m,), P (n,3), W (n,), map angle->parameter)``.
    """
    sweep = th1 - th0
    nseg = max(1, int(math.ceil(sweep / (0.5 * math.pi) - 1e-9)))
    d = sweep / nseg
    c = math.cos(0.5 * d)
    ends = th0 + d * np.arange(nseg + 1)
    ends[-1] = th1
    mids = th0 + d * (np.arange(nseg) + 0.5)
    ang = np.empty(2 * nseg + 1)
    ang[0::2] = ends
    ang[1::2] = mids
    scale = np.ones(2 * nseg + 1)
    scale[1::2] = 1.0 / c
    P = center + scale[:, None] * (np.cos(ang)[:, None] * X + np.sin(ang)[:, None] * Y)
    W = np.ones(2 * nseg + 1)
    W[1::2] = c
    full = abs(sweep - _TWO_PI) <= 1e-12 * _TWO_PI
    if full:
        P[-1] = P[0]
    U = np.concatenate([[th0] * 3, np.repeat(ends[1:-1], 2), [th1] * 3])
    return U, P, W, _angle_map(th0, th1, nseg)


def _angle_map(th0: float, th1: float, nseg: int) -> Callable[[np.ndarray], np.ndarray]:
    """Map an angle in ``[th0, th1]`` to the parameter of the arc built by :func:`_arc`.

    Inside segment ``k`` (sweep ``d``), the rational quadratic arc with middle
    weight ``cos(d/2)`` reaches the relative angle ``beta`` (from the segment
    middle) at ``s`` with ``tan(beta/2) = tan(d/4) (2 s - 1)``.  Angles off the
    range by a multiple of ``2 pi`` are wrapped, the rest clamped.
    """
    d = (th1 - th0) / nseg
    eps = 1e-7 * max(1.0, abs(th1 - th0))

    def pm(t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        lo = t < th0 - eps
        hi = t > th1 + eps
        if np.any(lo | hi):
            t = t.copy()
            up = t[lo] + _TWO_PI * np.ceil((th0 - eps - t[lo]) / _TWO_PI)
            t[lo] = np.where(up <= th1 + eps, up, t[lo])
            dn = t[hi] - _TWO_PI * np.ceil((t[hi] - th1 - eps) / _TWO_PI)
            t[hi] = np.where(dn >= th0 - eps, dn, t[hi])
        t = np.clip(t, th0, th1)
        k = np.clip(np.floor((t - th0) / d), 0, nseg - 1)
        beta = t - (th0 + (k + 0.5) * d)
        s = 0.5 * (1.0 + np.tan(0.5 * beta) / math.tan(0.25 * d))
        return th0 + (k + np.clip(s, 0.0, 1.0)) * d

    return pm


# ======================================================================
# low-level parsing
# ======================================================================
class _Unsupported(Exception):
    """An entity cannot be converted (unsupported child, unbounded plane, ...)."""


class _Holl(str):
    """A Hollerith string token."""


@dataclass
class _Entry:
    de: int
    etype: int
    pd_ptr: int
    transform: int
    status: tuple[int, int, int, int]
    form: int
    pd_count: int
    line: int  # file line of the first D line
    tokens: list | None = None
    tok_lines: list | None = None


def _split_lines(text: str) -> list[str]:
    if text.startswith("\ufeff"):
        text = text[1:]
    lines = re.split(r"\r\n|\r|\n", text)
    while lines and not lines[-1].strip():
        lines.pop()
    if len(lines) == 1 and len(lines[0]) > 80 and len(lines[0]) % 80 == 0:
        s = lines[0]
        lines = [s[i:i + 80] for i in range(0, len(s), 80)]
    return lines


def _tokenize(data: str, lines: Sequence[int], pdelim: str, rdelim: str, where: str) -> tuple[list, list, int]:
    """Split free-format parameter data into tokens (IGES 5.3 sec. 2.2.2).

    Args:
        data: concatenated data columns.
        lines: file line number of each character of ``data``.
        pdelim, rdelim: parameter and record delimiters.
        where: context for error messages.

    Returns:
        ``(tokens, token_lines, end)``: tokens are stripped strings ('' for an
        empty field) or :class:`_Holl`; ``end`` is the index after the record
        delimiter.
    """
    toks: list = []
    tlines: list = []
    i, n = 0, len(data)
    while True:
        j = i
        while j < n and data[j] == " ":
            j += 1
        if j >= n:
            raise IgesError(
                f"{where}: parameter data end without the record delimiter {rdelim!r} "
                f"(line {lines[-1] if lines else '?'}; truncated file?)"
            )
        m = _HOLL_RE.match(data, i)
        if m is not None and data[j].isdigit():
            cnt = int(m.group(1))
            s0 = m.end()
            if s0 + cnt > n:
                raise IgesError(
                    f"{where}: Hollerith string {cnt}H... at line {lines[j]} runs past the end of the data"
                )
            toks.append(_Holl(data[s0:s0 + cnt]))
            tlines.append(lines[j])
            k = s0 + cnt
            while k < n and data[k] == " ":
                k += 1
            if k >= n:
                raise IgesError(f"{where}: parameter data end without the record delimiter {rdelim!r} (truncated file?)")
            if data[k] == rdelim:
                return toks, tlines, k + 1
            if data[k] != pdelim:
                raise IgesError(
                    f"{where}: expected a delimiter after Hollerith string at line {lines[k]}, got {data[k]!r}"
                )
            i = k + 1
            continue
        kp = data.find(pdelim, i)
        kr = data.find(rdelim, i)
        if kr < 0 and kp < 0:
            raise IgesError(
                f"{where}: parameter data end without the record delimiter {rdelim!r} "
                f"(line {lines[-1] if lines else '?'}; truncated file?)"
            )
        if kr >= 0 and (kp < 0 or kr < kp):
            toks.append(data[i:kr].strip())
            tlines.append(lines[min(j, n - 1)])
            return toks, tlines, kr + 1
        toks.append(data[i:kp].strip())
        tlines.append(lines[min(j, n - 1)])
        i = kp + 1


def _to_float(tok, where: str) -> float:
    if isinstance(tok, _Holl) or not _NUM_RE.fullmatch(tok):
        raise IgesError(f"{where}: non-numeric value {str(tok)!r}")
    v = float(tok.replace("D", "E").replace("d", "e"))
    if not math.isfinite(v):
        raise IgesError(f"{where}: value {tok!r} is not finite (NaN/inf/overflow)")
    return v


class _Params:
    """Typed access to an entity's parameters with located error messages."""

    def __init__(self, e: _Entry):
        self.e = e
        self.t = e.tokens
        self.ln = e.tok_lines

    def where(self, i: int, name: str) -> str:
        line = self.ln[i] if i < len(self.ln) else (self.ln[-1] if self.ln else "?")
        return (f"DE {self.e.de} (entity {self.e.etype}), parameter {i} ({name}), "
                f"file line {line}")

    def has(self, i: int) -> bool:
        return i < len(self.t) and not (not isinstance(self.t[i], _Holl) and self.t[i] == "")

    def need(self, count: int, what: str) -> None:
        if len(self.t) < count:
            raise IgesError(
                f"DE {self.e.de} (entity {self.e.etype}, file line {self.e.line}): too few "
                f"parameters: {what} need {count - 1} values after the entity type, found "
                f"{len(self.t) - 1} (wrong knot vector length or truncated data?)"
            )

    def real(self, i: int, name: str, default: float | None = None) -> float:
        if not self.has(i):
            if default is None:
                raise IgesError(f"{self.where(i, name)}: missing value")
            return default
        return _to_float(self.t[i], self.where(i, name))

    def int(self, i: int, name: str, default: int | None = None) -> int:
        if not self.has(i):
            if default is None:
                raise IgesError(f"{self.where(i, name)}: missing value")
            return default
        tok = self.t[i]
        if not isinstance(tok, _Holl) and _INT_RE.fullmatch(tok):
            return int(tok)
        v = _to_float(tok, self.where(i, name))
        if v != int(v) or abs(v) > 2**31:
            raise IgesError(f"{self.where(i, name)}: expected an integer, got {str(tok)!r}")
        return int(v)

    def check_tail(self, start: int, what: str) -> None:
        """Tokens from ``start`` on must be the optional pointer lists ``NV, ptrs, NP, ptrs``."""
        T = len(self.t)
        i = start
        for name in ("NV (number of associativity pointers)", "NP (number of property pointers)"):
            if i >= T:
                return
            k = self.int(i, name)
            if k < 0:
                raise IgesError(f"{self.where(i, name)}: negative count {k}")
            i += 1 + k
        if i != T:
            raise IgesError(
                f"DE {self.e.de} (entity {self.e.etype}, file line {self.e.line}): {T - 1} parameters do not "
                f"match {what} (wrong knot vector length for degree and count?)"
            )

    def reals(self, i: int, count: int, name: str) -> np.ndarray:
        return np.array([self.real(i + k, f"{name}[{k}]") for k in range(count)], dtype=float)


# ======================================================================
# the reader
# ======================================================================
class _Reader:
    def __init__(self, text: str, source: str):
        self.source = source
        self.entries: dict[int, _Entry] = {}
        self.warn_msgs: dict[str, list[str]] = {}
        self.skipped: dict[int, int] = {}
        self.skip_reasons: dict[int, list[str]] = {}
        self.cache_c: dict[int, list[_C]] = {}
        self.cache_s: dict[int, object] = {}
        self.busy: set[int] = set()
        self.tcache: dict[int, tuple[np.ndarray, np.ndarray] | None] = {}
        self._parse_file(text)

    # ------------------------------------------------------------------
    def warn(self, key: str, msg: str) -> None:
        self.warn_msgs.setdefault(key, []).append(msg)

    def skip(self, etype: int, reason: str) -> None:
        self.skipped[etype] = self.skipped.get(etype, 0) + 1
        self.skip_reasons.setdefault(etype, []).append(reason)

    # ------------------------------------------------------------------
    def _parse_file(self, text: str) -> None:
        raw = _split_lines(text)
        if not raw:
            raise IgesError(f"{self.source}: empty file")
        order = "SGDPT"
        sections: dict[str, list[tuple[int, str]]] = {c: [] for c in order}
        last = -1
        for ln, line in enumerate(raw, start=1):
            line = line.rstrip()
            if not line:
                continue
            if len(line) > 80:
                raise IgesError(
                    f"line {ln}: {len(line)} characters; fixed-format IGES lines have 80 columns "
                    f"(wrong column layout)"
                )
            line = line.ljust(80)
            c = line[72]
            if c in "BCF":
                raise IgesError(f"line {ln}: binary/compressed IGES (section {c!r}) is not supported")
            if c not in order:
                raise IgesError(
                    f"line {ln}: column 73 holds {c!r}, not a section letter S/G/D/P/T "
                    f"(wrong column layout: is this fixed-format 80-column IGES?)"
                )
            k = order.index(c)
            if k < last:
                raise IgesError(
                    f"line {ln}: section {c!r} after section {order[last]!r} "
                    f"(sections must come in the order S, G, D, P, T)"
                )
            if c == "T" and sections["T"]:
                raise IgesError(f"line {ln}: more than one Terminate (T) record")
            last = k
            sections[c].append((ln, line))
        if not sections["T"]:
            lastc = order[last] if last >= 0 else "?"
            raise IgesError(
                f"{self.source}: truncated file: no Terminate (T) record (the last line, {len(raw)}, "
                f"is in section {lastc!r})"
            )
        for c in "SGDP":
            for i, (ln, s) in enumerate(sections[c]):
                f = s[73:80].strip()
                if not (f.isdigit() and int(f) == i + 1):
                    self.warn("seq", f"line {ln}: sequence number {f!r} in section {c}, expected {i + 1}")
                    break
        self._check_terminate(sections)
        if not sections["G"]:
            raise IgesError(f"{self.source}: no Global (G) section")
        self._parse_global(sections["G"])
        self._parse_directory(sections["D"])
        self.plines = sections["P"]
        self.pback: list[int] = []
        for ln, s in self.plines:
            f = s[64:72].strip()
            if not _INT_RE.fullmatch(f):
                raise IgesError(
                    f"line {ln}: parameter-data line has {s[64:72]!r} in columns 65-72, expected the "
                    f"DE back-pointer (wrong column layout)"
                )
            self.pback.append(int(f))

    def _check_terminate(self, sections) -> None:
        ln, t = sections["T"][0]
        counts = {}
        for k, c in enumerate("SGDP"):
            fld = t[8 * k:8 * k + 8]
            if fld[0] != c or not fld[1:].strip().isdigit():
                raise IgesError(
                    f"line {ln}: Terminate record field {k + 1} is {fld!r}, expected '{c}' and a count "
                    f"in columns {8 * k + 1}-{8 * k + 8}"
                )
            counts[c] = int(fld[1:])
        for c in "SGDP":
            have = len(sections[c])
            if counts[c] != have:
                raise IgesError(
                    f"line {ln}: Terminate record says section {c} has {counts[c]} lines, the file has "
                    f"{have} (truncated or corrupted file)"
                )

    def _parse_global(self, glines) -> None:
        data = "".join(s[:72] for _, s in glines)
        lines = [ln for ln, _ in glines for _ in range(72)]
        i = 0
        while i < len(data) and data[i] == " ":
            i += 1

        def delim(i: int, default: str, name: str) -> tuple[str, int, bool]:
            if data.startswith("1H", i) or data.startswith("1h", i):
                if i + 2 >= len(data):
                    raise IgesError(f"line {lines[-1]}: Global section truncated in the {name} delimiter")
                return data[i + 2], i + 3, True
            return default, i, False

        pd, i, given = delim(i, ",", "parameter")
        if given:
            if i >= len(data) or data[i] != pd:
                raise IgesError(
                    f"line {glines[0][0]}: Global parameter 1 (parameter delimiter) must be "
                    f"'1H{pd}' followed by {pd!r}"
                )
        elif data[i:i + 1] != ",":
            raise IgesError(
                f"line {glines[0][0]}: Global section must start with the parameter delimiter "
                f"('1H,' or an empty field), got {data[i:i + 10]!r}"
            )
        i += 1
        while i < len(data) and data[i] == " ":
            i += 1
        rd, i2, given = delim(i, ";", "record")
        if pd == rd or pd in " 0123456789+-.Hh" or rd in " 0123456789+-.Hh":
            raise IgesError(f"line {glines[0][0]}: invalid delimiters {pd!r} / {rd!r} in the Global section")
        self.pdelim, self.rdelim = pd, rd
        if given:
            rest, rlines = data[i2:], lines[i2:]
            if rest[:1] == rd:
                toks = []
            else:
                if rest[:1] != pd:
                    raise IgesError(
                        f"line {glines[0][0]}: Global parameter 2 (record delimiter) must be "
                        f"'1H{rd}' followed by {pd!r}"
                    )
                toks, _, _ = _tokenize(rest[1:], rlines[1:], pd, rd, "Global section")
        else:
            toks, _, _ = _tokenize(data[i:], lines[i:], pd, rd, "Global section")
            toks = toks[1:] if toks else toks  # field 2 (empty)
        g = [None, None] + list(toks)  # g[k] = Global parameter k+1
        def gp(k):
            return g[k - 1] if k - 1 < len(g) else None
        flag_tok = gp(14)
        flag = 1
        if flag_tok not in (None, "") and not isinstance(flag_tok, _Holl):
            try:
                flag = int(_to_float(flag_tok, "Global parameter 14 (unit flag)"))
            except IgesError as exc:
                raise IgesError(f"line {glines[0][0]}: {exc}") from None
        name = gp(15)
        if isinstance(name, _Holl) and name.strip():
            units = name.strip().upper()
        else:
            units = UNIT_FLAGS.get(flag, "INCH")
        self.unit_flag, self.units = flag, units

    def _parse_directory(self, dlines) -> None:
        if len(dlines) % 2:
            raise IgesError(
                f"line {dlines[-1][0]}: odd number of Directory Entry lines ({len(dlines)}); "
                f"each entry has two lines (truncated file?)"
            )
        names1 = ["entity type", "parameter data pointer", "structure", "line font", "level",
                  "view", "transformation matrix", "label display"]
        names2 = ["entity type", "line weight", "colour", "parameter line count", "form number"]
        for k in range(0, len(dlines), 2):
            (l1, s1), (l2, s2) = dlines[k], dlines[k + 1]
            de = k + 1

            def fld(s, i, ln, name):
                f = s[8 * i:8 * i + 8].strip()
                if f == "":
                    return 0
                if not _INT_RE.fullmatch(f):
                    raise IgesError(
                        f"DE {de}, line {ln}: directory field '{name}' (columns {8 * i + 1}-{8 * i + 8}) "
                        f"is {f!r}, not an integer"
                    )
                return int(f)

            v1 = [fld(s1, i, l1, names1[i]) for i in range(8)]
            v2 = [fld(s2, i, l2, names2[i]) for i in range(5)]
            st = s1[64:72].replace(" ", "0")
            if not st.isdigit():
                raise IgesError(f"DE {de}, line {l1}: status number {s1[64:72]!r} is not numeric")
            if v1[0] != v2[0]:
                raise IgesError(
                    f"DE {de}, lines {l1}-{l2}: entity type {v1[0]} on the first line but {v2[0]} on the second"
                )
            self.entries[de] = _Entry(
                de=de, etype=v1[0], pd_ptr=v1[1], transform=v1[6],
                status=(int(st[0:2]), int(st[2:4]), int(st[4:6]), int(st[6:8])),
                form=v2[4], pd_count=v2[3], line=l1,
            )

    # ------------------------------------------------------------------
    def entry(self, de: int, ctx: str) -> _Entry:
        e = self.entries.get(de)
        if e is None:
            raise IgesError(f"{ctx}: pointer {de} does not point to a directory entry")
        return e

    def params(self, e: _Entry) -> _Params:
        if e.tokens is None:
            nP = len(self.plines)
            if not 1 <= e.pd_ptr <= nP:
                raise IgesError(
                    f"DE {e.de} (entity {e.etype}, line {e.line}): parameter data pointer {e.pd_ptr} is "
                    f"outside the P section (1..{nP})"
                )
            a = e.pd_ptr - 1
            cnt = e.pd_count
            if cnt < 1 or a + cnt > nP:
                b = a
                while b < nP and self.pback[b] == e.de:
                    b += 1
                if b == a:
                    raise IgesError(
                        f"DE {e.de} (entity {e.etype}, line {e.line}): parameter line count {cnt} is invalid "
                        f"and no P line at {e.pd_ptr} points back to it"
                    )
                self.warn("count", f"DE {e.de}: parameter line count {cnt} replaced by {b - a}")
                cnt = b - a
            sl = self.plines[a:a + cnt]
            if any(self.pback[a + i] != e.de for i in range(cnt)):
                self.warn("backptr", f"DE {e.de}: P lines {e.pd_ptr}..{e.pd_ptr + cnt - 1} do not all point back to it")
            data = "".join(s[:64] for _, s in sl)
            lines = [ln for ln, _ in sl for _ in range(64)]
            toks, tl, _ = _tokenize(data, lines, self.pdelim, self.rdelim,
                                    f"DE {e.de} (entity {e.etype})")
            if not toks or isinstance(toks[0], _Holl) or not _INT_RE.fullmatch(toks[0]) or int(toks[0]) != e.etype:
                raise IgesError(
                    f"DE {e.de} (line {e.line}): parameter data (P line {e.pd_ptr}) starts with "
                    f"{(toks[0] if toks else '')!r}, not the entity type {e.etype}"
                )
            e.tokens, e.tok_lines = toks, tl
        return _Params(e)

    # ------------------------------------------------------------------
    def transform_of(self, e: _Entry) -> tuple[np.ndarray, np.ndarray] | None:
        """Composed 124 matrix for DE field 7 of ``e``: ``x -> R x + t``, or None."""
        if e.transform == 0:
            return None
        if e.transform < 0:
            raise IgesError(f"DE {e.de} (entity {e.etype}): negative transformation matrix pointer {e.transform}")
        chain = []
        de = e.transform
        seen = set()
        while de:
            if de in seen:
                raise IgesError(f"DE {e.de}: circular chain of transformation matrices at DE {de}")
            seen.add(de)
            t = self.entry(de, f"DE {e.de} (entity {e.etype}) transformation matrix")
            if t.etype != 124:
                raise IgesError(
                    f"DE {e.de} (entity {e.etype}): transformation pointer {de} points to entity "
                    f"{t.etype}, not 124"
                )
            if de not in self.tcache:
                pr = self.params(t)
                pr.need(13, "a 124 transformation matrix")
                m = pr.reals(1, 12, "R/T").reshape(3, 4)
                self.tcache[de] = (m[:, :3].copy(), m[:, 3].copy())
            chain.append(self.tcache[de])
            de = t.transform
            if de < 0:
                raise IgesError(f"DE {t.de} (entity 124): negative transformation matrix pointer")
        R, T = np.eye(3), np.zeros(3)
        for Ri, Ti in chain:  # x -> T2(T1(x))
            R, T = Ri @ R, Ri @ T + Ti
        return R, T

    @staticmethod
    def _apply(tr, Pw: np.ndarray) -> np.ndarray:
        if tr is None:
            return Pw
        R, T = tr
        out = Pw.copy()
        out[..., :3] = Pw[..., :3] @ R.T + Pw[..., 3:] * T
        return out

    def _enter(self, e: _Entry, depth: int) -> None:
        if depth > _MAX_DEPTH:
            raise IgesError(f"DE {e.de} (entity {e.etype}): entities nested more than {_MAX_DEPTH} deep")
        if e.de in self.busy:
            raise IgesError(f"DE {e.de} (entity {e.etype}): circular reference between entities")
        self.busy.add(e.de)

    # ------------------------------------------------------------------
    # curves
    # ------------------------------------------------------------------
    def curve_pieces(self, de: int, ctx: str, depth: int = 0) -> list[_C]:
        """Pieces (one unless a 102 has gaps) of a curve entity, own transform applied."""
        e = self.entry(de, ctx)
        if de in self.cache_c:
            return self.cache_c[de]
        self._enter(e, depth)
        try:
            if e.etype == 126:
                pieces = [self._c126(e)]
            elif e.etype == 110:
                pieces = [self._c110(e)]
            elif e.etype == 100:
                pieces = [self._c100(e)]
            elif e.etype == 102:
                pieces = self._c102(e, depth)
            elif e.etype == 142:
                pr = self.params(e)
                pr.need(5, "a 142 curve on surface")
                cptr = pr.int(4, "CPTR", 0)
                if cptr == 0:
                    raise _Unsupported("142 curve on surface without a model-space curve")
                pieces = self.curve_pieces(cptr, f"DE {de} (entity 142) CPTR", depth + 1)
            else:
                raise _Unsupported(f"curve entity type {e.etype} is not supported")
            tr = self.transform_of(e)
            if tr is not None:
                pieces = [_C(c.p, c.U, self._apply(tr, c.Pw), c.pmap) for c in pieces]
        finally:
            self.busy.discard(de)
        self.cache_c[de] = pieces
        return pieces

    def _c126(self, e: _Entry) -> _C:
        pr = self.params(e)
        pr.need(3, "a 126 curve (K, M)")
        K = pr.int(1, "K (upper index of sum)")
        M = pr.int(2, "M (degree)")
        if M < 1:
            raise IgesError(f"{pr.where(2, 'M')}: degree must be >= 1, got {M}")
        if K < M:
            raise IgesError(
                f"{pr.where(1, 'K')}: K={K} gives {K + 1} control points, fewer than degree+1 = {M + 1}"
            )
        n, m = K + 1, K + M + 2
        A = 7
        pr.need(A + m + n + 3 * n, f"K={K}, M={M}: {m} knots, {n} weights and {n} control points")
        iv = A + m + 4 * n
        after = len(pr.t) - iv
        what = f"K={K}, M={M} ({m} knots, {n} weights, {n} points, V(0), V(1), normal)"
        if after >= 5:
            pr.check_tail(iv + 5, what)
        elif after not in (0, 2):
            raise IgesError(
                f"DE {e.de} (entity 126, file line {e.line}): {after} values after the control points, "
                f"expected 0, 2 or 5: the parameter count does not match {what} "
                f"(wrong knot vector length for degree and count?)"
            )
        U = pr.reals(A, m, "knot T")
        W = pr.reals(A + m, n, "weight W")
        P = pr.reals(A + m + n, 3 * n, "control point").reshape(n, 3)
        self._check_knots(pr, A, U, M, n, "knot vector T")
        self._check_weights(pr, A + m, W)
        c = _C(M, U, _homog(P, W), None, (P, W))
        if pr.has(iv) and pr.has(iv + 1):
            v0, v1 = pr.real(iv, "V(0)"), pr.real(iv + 1, "V(1)")
            Ur, Pw = self._range(e, M, U, c.Pw, v0, v1, "V(0), V(1)")
            if Ur is not U:
                c = _C(M, Ur, Pw)
        return c

    def _check_knots(self, pr: _Params, at: int, U: np.ndarray, p: int, n: int, name: str) -> None:
        d = np.diff(U)
        if np.any(d < 0):
            i = int(np.flatnonzero(d < 0)[0])
            raise IgesError(
                f"{pr.where(at + i + 1, name)}: {name} is decreasing ({U[i]!r} > {U[i + 1]!r}) "
                f"at index {i + 1}"
            )
        if not U[p] < U[n]:
            raise IgesError(
                f"{pr.where(at, name)}: {name} has an empty parameter domain "
                f"[T({p}), T({n})] = [{U[p]!r}, {U[n]!r}] for degree {p} and {n} control points"
            )
        supp = U[p + 1:] - U[:n]
        if np.any(supp <= 0):
            i = int(np.flatnonzero(supp <= 0)[0])
            raise IgesError(
                f"{pr.where(at + i, name)}: {name}: knot {U[i]!r} repeated more than degree+1 = {p + 1} times"
            )

    def _check_weights(self, pr: _Params, at: int, W: np.ndarray) -> None:
        bad = np.flatnonzero(W.ravel() <= 0)
        if bad.size:
            i = int(bad[0])
            raise IgesError(f"{pr.where(at + i, 'weight')}: weights must be positive, W[{i}] = {W.ravel()[i]!r}")

    def _range(self, e: _Entry, p: int, U: np.ndarray, Pw: np.ndarray, a: float, b: float, name: str):
        n = Pw.shape[0]
        ka, kb = _domain(p, U, n)
        tol = 1e-10 * (kb - ka) + 1e-300
        if abs(a - ka) <= tol and abs(b - kb) <= tol:
            return U, Pw
        if ka - tol <= a < b <= kb + tol and b - a > tol:
            return _restrict(p, U, Pw, max(a, ka), min(b, kb))
        self.warn("range", f"DE {e.de} (entity {e.etype}): parameter range {name} = [{a!r}, {b!r}] does not fit "
                           f"the knot domain [{ka!r}, {kb!r}]; the knot domain is used")
        return U, Pw

    def _c110(self, e: _Entry) -> _C:
        pr = self.params(e)
        pr.need(7, "a 110 line")
        P = pr.reals(1, 6, "X1,Y1,Z1,X2,Y2,Z2").reshape(2, 3)
        if e.form != 0:
            self.warn("line_form", f"DE {e.de}: unbounded line (110 form {e.form}) used as the segment P1-P2")
        if np.all(P[0] == P[1]):
            raise IgesError(f"DE {e.de} (entity 110, line {e.line}): degenerate line, both end points are {P[0].tolist()}")
        return _C(1, np.array([0.0, 0.0, 1.0, 1.0]), _homog(P, np.ones(2)))

    def _c100(self, e: _Entry) -> _C:
        pr = self.params(e)
        pr.need(8, "a 100 circular arc")
        zt = pr.real(1, "ZT")
        x = pr.reals(2, 6, "X1,Y1,X2,Y2,X3,Y3")
        c, s, t = x[0:2], x[2:4], x[4:6]
        r = float(np.hypot(*(s - c)))
        if not r > 0:
            raise IgesError(f"DE {e.de} (entity 100, line {e.line}): zero radius (start point = centre)")
        th0 = math.atan2(s[1] - c[1], s[0] - c[0])
        if float(np.hypot(*(t - s))) <= 1e-12 * r:
            th1 = th0 + _TWO_PI
        else:
            th1 = math.atan2(t[1] - c[1], t[0] - c[0])
            while th1 <= th0:
                th1 += _TWO_PI
            while th1 - th0 > _TWO_PI:
                th1 -= _TWO_PI
        U, P, W, pm = _arc(np.array([c[0], c[1], zt]), np.array([r, 0.0, 0.0]), np.array([0.0, r, 0.0]), th0, th1)
        return _C(2, U, _homog(P, W), pm)

    def _c102(self, e: _Entry, depth: int) -> list[_C]:
        pr = self.params(e)
        pr.need(2, "a 102 composite curve (N)")
        N = pr.int(1, "N")
        if N < 1:
            raise IgesError(f"{pr.where(1, 'N')}: composite curve with {N} segments")
        pr.need(2 + N, f"N={N} segment pointers")
        segs: list[_C] = []
        for k in range(N):
            ptr = pr.int(2 + k, f"DE({k + 1})")
            segs.extend(self.curve_pieces(ptr, f"DE {e.de} (entity 102) segment {k + 1}", depth + 1))
        return segs

    # ------------------------------------------------------------------
    def join(self, pieces: list[_C], de: int) -> list[_C]:
        """Join consecutive pieces that meet into single NURBS (C0 joints)."""
        if len(pieces) == 1:
            return pieces
        pieces = [_clamp_curve(c) for c in pieces]
        P = np.concatenate([_cart(c.Pw)[0] for c in pieces])
        size = float(np.linalg.norm(P.max(0) - P.min(0))) or 1.0
        tol = 1e-7 * size
        runs: list[list[_C]] = [[pieces[0]]]
        for c in pieces[1:]:
            a = _cart(runs[-1][-1].Pw[-1])[0]
            b = _cart(c.Pw[0])[0]
            if np.linalg.norm(a - b) <= tol:
                runs[-1].append(c)
            else:
                runs.append([c])
        if len(runs) > 1:
            self.warn("gap", f"DE {de} (entity 102): segments do not meet; split into {len(runs)} curves")
        out = []
        for run in runs:
            pmax = max(c.p for c in run)
            run = [_elevate(c, pmax - c.p) for c in run]
            U = run[0].U.copy()
            Pw = run[0].Pw.copy()
            for c in run[1:]:
                wa = Pw[-1, 3]
                cPw = c.Pw * (wa / c.Pw[0, 3])
                mid = 0.5 * (Pw[-1, :3] + cPw[0, :3])
                Pw[-1, :3] = mid
                shift = U[-1] - c.U[0]
                U = np.concatenate([U[:-1], c.U[pmax + 1:] + shift])
                Pw = np.concatenate([Pw, cPw[1:]])
            out.append(_C(pmax, U, Pw))
        return out

    def single_curve(self, de: int, ctx: str, depth: int) -> _C:
        pieces = self.curve_pieces(de, ctx, depth)
        if len(pieces) == 1:
            return pieces[0]
        j = self.join(pieces, de)
        if len(j) != 1:
            raise _Unsupported(f"{ctx}: composite curve with gaps")
        # parameter map of the joined composite: per piece, shifted
        starts = []
        t = pieces[0].U[pieces[0].p]
        for c in pieces:
            a, b = _domain(c.p, c.U, c.Pw.shape[0])
            starts.append((t, t + (b - a), a, c.pmap))
            t += b - a

        def pm(x: np.ndarray) -> np.ndarray:
            x = np.asarray(x, dtype=float)
            out = x.copy()
            for k, (t0, t1, a, sub) in enumerate(starts):
                sel = (x >= t0) if k == 0 else (x > t0)
                if k < len(starts) - 1:
                    sel &= x <= t1
                if sub is not None and np.any(sel):
                    out[sel] = sub(x[sel] - t0 + a) - a + t0
            return out

        c = j[0]
        return _C(c.p, c.U, c.Pw, pm if any(s[3] is not None for s in starts) else None)

    def sample_pieces(self, pieces: list[_C], de: int) -> np.ndarray:
        """Polygon through points of the pieces, ``(k, 3)``, consecutive duplicates removed."""
        pts = []
        for c in pieces:
            crv = self.to_curve(c, de)
            k = crv.distinct_knots
            per = 8 if c.p == 1 else 16
            t = np.concatenate([np.linspace(k[i], k[i + 1], per, endpoint=False) for i in range(len(k) - 1)]
                               + [k[-1:]])
            pts.append(crv.evaluate(t)[0])
        P = np.concatenate(pts)
        keep = np.ones(len(P), bool)
        scale = float(np.linalg.norm(P.max(0) - P.min(0))) or 1.0
        keep[1:] = np.linalg.norm(np.diff(P, axis=0), axis=1) > 1e-12 * scale
        P = P[keep]
        if len(P) > 1 and np.linalg.norm(P[-1] - P[0]) <= 1e-12 * scale:
            P = P[:-1]
        return P

    def _finite(self, Pw: np.ndarray, de: int) -> None:
        if not np.all(np.isfinite(Pw)):
            et = self.entries[de].etype if de in self.entries else "?"
            raise IgesError(
                f"DE {de} (entity {et}): control points times weights overflow (values too large)"
            )

    def to_curve(self, c: _C, de: int) -> NurbsCurve:
        self._finite(c.Pw, de)
        P, W = c.exact if c.exact is not None else _cart(c.Pw)
        try:
            return NurbsCurve(degree=c.p, knots=c.U, control_points=P, weights=W)
        except NurbsError as exc:
            raise IgesError(f"DE {de} ({self.entries[de].etype if de in self.entries else '?'}): invalid NURBS: {exc}") from None

    # ------------------------------------------------------------------
    # surfaces
    # ------------------------------------------------------------------
    def surface(self, de: int, ctx: str, depth: int = 0):
        """``_S`` (own transform applied) or a plane tuple ``('plane', o, e1, e2, bound_pieces)``."""
        e = self.entry(de, ctx)
        if de in self.cache_s:
            return self.cache_s[de]
        self._enter(e, depth)
        try:
            if e.etype == 128:
                s = self._s128(e)
            elif e.etype == 120:
                s = self._s120(e, depth)
            elif e.etype == 122:
                s = self._s122(e, depth)
            elif e.etype == 108:
                s = self._s108(e, depth)
            else:
                raise _Unsupported(f"surface entity type {e.etype} is not supported")
            tr = self.transform_of(e)
            if tr is not None:
                if isinstance(s, _S):
                    s = s._replace(Pw=self._apply(tr, s.Pw), exact=None)
                else:
                    R, T = tr
                    bound = None if s[4] is None else [c._replace(Pw=self._apply(tr, c.Pw), exact=None) for c in s[4]]
                    s = ("plane", R @ s[1] + T, R @ s[2], R @ s[3], bound)
        finally:
            self.busy.discard(de)
        self.cache_s[de] = s
        return s

    def _s128(self, e: _Entry) -> _S:
        pr = self.params(e)
        pr.need(5, "a 128 surface (K1, K2, M1, M2)")
        K1, K2 = pr.int(1, "K1"), pr.int(2, "K2")
        M1, M2 = pr.int(3, "M1 (degree u)"), pr.int(4, "M2 (degree v)")
        for K, M, nm in ((K1, M1, "1"), (K2, M2, "2")):
            if M < 1:
                raise IgesError(f"{pr.where(2 + int(nm), 'M' + nm)}: degree must be >= 1, got {M}")
            if K < M:
                raise IgesError(
                    f"{pr.where(int(nm), 'K' + nm)}: K{nm}={K} gives {K + 1} control points, fewer than "
                    f"degree+1 = {M + 1}"
                )
        n1, n2 = K1 + 1, K2 + 1
        a1, a2 = K1 + M1 + 2, K2 + M2 + 2
        A = 10
        N = n1 * n2
        pr.need(A + a1 + a2 + 4 * N,
                f"K1={K1}, K2={K2}, M1={M1}, M2={M2}: {a1}+{a2} knots, {N} weights and {N} control points")
        iv = A + a1 + a2 + 4 * N
        after = len(pr.t) - iv
        what = (f"K1={K1}, K2={K2}, M1={M1}, M2={M2} ({a1}+{a2} knots, {N} weights, {N} points, "
                f"U(0), U(1), V(0), V(1))")
        if after >= 4:
            pr.check_tail(iv + 4, what)
        elif after != 0:
            raise IgesError(
                f"DE {e.de} (entity 128, file line {e.line}): {after} values after the control points, "
                f"expected 0 or 4: the parameter count does not match {what} "
                f"(wrong knot vector length for degree and count?)"
            )
        S = pr.reals(A, a1, "knot S")
        T = pr.reals(A + a1, a2, "knot T")
        Wf = pr.reals(A + a1 + a2, N, "weight W")
        Pf = pr.reals(A + a1 + a2 + N, 3 * N, "control point")
        self._check_knots(pr, A, S, M1, n1, "knot vector S (u)")
        self._check_knots(pr, A + a1, T, M2, n2, "knot vector T (v)")
        self._check_weights(pr, A + a1 + a2, Wf)
        W = Wf.reshape(n2, n1).T
        P = Pf.reshape(n2, n1, 3).transpose(1, 0, 2)
        Pw = _homog(P, W)
        if all(pr.has(iv + k) for k in range(4)):
            u0, u1, v0, v1 = (pr.real(iv + k, nm) for k, nm in enumerate(("U(0)", "U(1)", "V(0)", "V(1)")))
            S2, Pw = self._range(e, M1, S, Pw, u0, u1, "U(0), U(1)")
            T2, Pwt = self._range(e, M2, T, Pw.transpose(1, 0, 2), v0, v1, "V(0), V(1)")
            if S2 is not S or T2 is not T:
                return _S(M1, M2, S2, T2, np.ascontiguousarray(Pwt.transpose(1, 0, 2)))
        return _S(M1, M2, S, T, Pw, None, (P, W))

    def _axis(self, de: int, ctx: str, depth: int) -> tuple[np.ndarray, np.ndarray]:
        e = self.entry(de, ctx)
        if e.etype != 110:
            raise IgesError(f"{ctx}: axis must be a line (entity 110), DE {de} is entity {e.etype}")
        c = self.curve_pieces(de, ctx, depth)[0]
        P, _ = _cart(c.Pw)
        return P[0], P[-1]

    def _s120(self, e: _Entry, depth: int) -> _S:
        pr = self.params(e)
        pr.need(5, "a 120 surface of revolution (L, C, SA, TA)")
        L, C = pr.int(1, "L (axis)"), pr.int(2, "C (generatrix)")
        SA, TA = pr.real(3, "SA"), pr.real(4, "TA")
        if not TA > SA:
            raise IgesError(f"{pr.where(4, 'TA')}: terminate angle {TA!r} must exceed start angle {SA!r}")
        if TA - SA > _TWO_PI * (1 + 1e-8):
            raise IgesError(f"{pr.where(4, 'TA')}: rotation TA - SA = {TA - SA!r} exceeds 2 pi")
        if abs(TA - SA - _TWO_PI) <= 1e-8 * _TWO_PI:
            TA = SA + _TWO_PI  # full revolution written with rounded 2 pi
        P1, P2 = self._axis(L, f"DE {e.de} (entity 120) axis", depth + 1)
        d = P2 - P1
        nd = float(np.linalg.norm(d))
        if not nd > 0:
            raise IgesError(f"DE {e.de} (entity 120, line {e.line}): axis line has zero length")
        D = d / nd
        g = _clamp_curve(self.single_curve(C, f"DE {e.de} (entity 120) generatrix", depth + 1))
        Pg, Wg = _cart(g.Pw)
        O = P1 + np.outer((Pg - P1) @ D, D)
        X = Pg - O
        Y = np.cross(D, X)
        Uv, Pa, Wa, vmap = _arc(np.zeros(3), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), SA, TA)
        ca, sa = Pa[:, 0], Pa[:, 1]  # includes the 1/cos scaling of the middle points
        net = O[:, None, :] + ca[None, :, None] * X[:, None, :] + sa[None, :, None] * Y[:, None, :]
        if abs(TA - SA - _TWO_PI) <= 1e-15:
            net[:, -1] = net[:, 0]
        Wn = Wg[:, None] * Wa[None, :]
        gmap = g.pmap

        def pm(uv: np.ndarray) -> np.ndarray:
            uv = np.array(uv, dtype=float)
            if gmap is not None:
                uv[:, 0] = gmap(uv[:, 0])
            uv[:, 1] = vmap(uv[:, 1])
            return uv

        return _S(g.p, 2, g.U, Uv, _homog(net, Wn), pm)

    def _s122(self, e: _Entry, depth: int) -> _S:
        pr = self.params(e)
        pr.need(5, "a 122 tabulated cylinder (DE, LX, LY, LZ)")
        ptr = pr.int(1, "DE (directrix)")
        Lp = pr.reals(2, 3, "LX,LY,LZ")
        g = _clamp_curve(self.single_curve(ptr, f"DE {e.de} (entity 122) directrix", depth + 1))
        Pg, Wg = _cart(g.Pw)
        Dv = Lp - Pg[0]
        if not np.linalg.norm(Dv) > 0:
            raise IgesError(f"DE {e.de} (entity 122, line {e.line}): generatrix has zero length")
        net = np.stack([Pg, Pg + Dv], axis=1)
        Wn = np.stack([Wg, Wg], axis=1)
        t0, t1 = float(g.U[0]), float(g.U[-1])
        gmap = g.pmap

        def pm(uv: np.ndarray) -> np.ndarray:  # IGES 5.3: u in [0,1] along the directrix
            uv = np.array(uv, dtype=float)
            t = t0 + uv[:, 0] * (t1 - t0)
            uv[:, 0] = gmap(t) if gmap is not None else t
            return uv

        return _S(g.p, 1, g.U, np.array([0.0, 0.0, 1.0, 1.0]), _homog(net, Wn), pm)

    def _s108(self, e: _Entry, depth: int):
        pr = self.params(e)
        pr.need(5, "a 108 plane (A, B, C, D)")
        abc = pr.reals(1, 3, "A,B,C")
        Dc = pr.real(4, "D")
        nn = float(np.linalg.norm(abc))
        if not nn > 0:
            raise IgesError(f"DE {e.de} (entity 108, line {e.line}): plane normal (A,B,C) is zero")
        nrm = abc / nn
        o = nrm * (Dc / nn)
        k = int(np.argmin(np.abs(nrm)))
        ax = np.zeros(3)
        ax[k] = 1.0
        e1 = np.cross(nrm, ax)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(nrm, e1)
        ptr = pr.int(5, "PTR (bounding curve)", 0)
        bound = None
        if ptr != 0 and e.form != 0:
            bound = self.curve_pieces(ptr, f"DE {e.de} (entity 108) bounding curve", depth + 1)
        return ("plane", o, e1, e2, bound)

    def plane_patch(self, pl, boundary: list[_C] | None, de: int) -> tuple[_S, np.ndarray]:
        """Bilinear patch over the boundary's control points, and the boundary polygon in (u,v)."""
        if boundary is None:
            raise _Unsupported("unbounded plane (108 without a bounding curve)")
        _, o, e1, e2, _ = pl
        e1 = e1 / np.linalg.norm(e1)
        e2 = e2 - (e2 @ e1) * e1
        n2 = np.linalg.norm(e2)
        if not n2 > 0:
            raise IgesError(f"DE {de}: degenerate plane after transformation")
        e2 = e2 / n2
        Pc = np.concatenate([_cart(c.Pw)[0] for c in boundary]) - o
        uvc = np.stack([Pc @ e1, Pc @ e2], axis=1)
        lo, hi = uvc.min(0), uvc.max(0)
        if not np.all(hi > lo):
            raise IgesError(f"DE {de}: the plane's bounding curve has no area")
        poly3 = self.sample_pieces(boundary, de) - o
        poly = np.stack([poly3 @ e1, poly3 @ e2], axis=1)
        net = np.empty((2, 2, 3))
        for i in range(2):
            for j in range(2):
                net[i, j] = o + (lo[0] if i == 0 else hi[0]) * e1 + (lo[1] if j == 0 else hi[1]) * e2
        U = np.array([lo[0], lo[0], hi[0], hi[0]])
        V = np.array([lo[1], lo[1], hi[1], hi[1]])
        return _S(1, 1, U, V, _homog(net, np.ones((2, 2)))), poly

    def to_surface(self, s: _S, de: int) -> NurbsSurface:
        self._finite(s.Pw, de)
        P, W = s.exact if s.exact is not None else _cart(s.Pw)
        try:
            return NurbsSurface(degree_u=s.p, degree_v=s.q, knots_u=s.U, knots_v=s.V,
                                control_points=P, weights=W)
        except NurbsError as exc:
            raise IgesError(f"DE {de} ({self.entries[de].etype if de in self.entries else '?'}): invalid NURBS: {exc}") from None

    # ------------------------------------------------------------------
    def _loop_142(self, de142: int, ctx: str) -> tuple[int, int]:
        """``(BPTR, CPTR)`` of a 142 curve on a parametric surface (IGES 5.3 sec. 4.32)."""
        e = self.entry(de142, ctx)
        if e.etype != 142:
            raise IgesError(f"{ctx}: DE {de142} is entity {e.etype}, expected 142 (curve on a parametric surface)")
        pr = self.params(e)
        pr.need(6, "a 142 curve on surface (CRTN, SPTR, BPTR, CPTR, PREF)")
        return pr.int(3, "BPTR", 0), pr.int(4, "CPTR", 0)

    def trimmed(self, e: _Entry, depth: int = 0):
        """Surface, outer loop and holes of a 144 trimmed surface."""
        pr = self.params(e)
        pr.need(5, "a 144 trimmed surface (PTS, N1, N2, PTO)")
        pts = pr.int(1, "PTS")
        n1 = pr.int(2, "N1", 0)
        n2 = pr.int(3, "N2", 0)
        pto = pr.int(4, "PTO", 0)
        if n2 < 0:
            raise IgesError(f"{pr.where(3, 'N2')}: negative number of inner boundaries {n2}")
        pr.need(5 + n2, f"N2={n2} inner boundary pointers")
        ptis = [pr.int(5 + k, f"PTI({k + 1})") for k in range(n2)]
        s = self.surface(pts, f"DE {e.de} (entity 144) PTS", depth + 1)
        tr = self.transform_of(e)
        ctx = f"DE {e.de} (entity 144)"
        loops_ptr = ([pto] if (n1 != 0 and pto != 0) else []) + ptis
        is_plane = not isinstance(s, _S)
        loops3: list[list[_C] | None] = []
        loops2: list[list[_C] | None] = []
        for k, ptr in enumerate(loops_ptr):
            bptr, cptr = self._loop_142(ptr, f"{ctx} boundary {k}")
            c2 = c3 = None
            try:  # planes: model-space curve; other surfaces: parameter-space curve
                if is_plane and cptr:
                    c3 = self.curve_pieces(cptr, f"{ctx} CPTR", depth + 2)
                elif not is_plane and bptr:
                    c2 = self.curve_pieces(bptr, f"{ctx} BPTR", depth + 2)
            except _Unsupported:
                pass
            loops3.append(c3)
            loops2.append(c2)
        outer_given = bool(n1 != 0 and pto != 0)
        if is_plane:
            bound = loops3[0] if outer_given else s[4]
            if bound is None:
                raise _Unsupported("trimmed plane without a model-space outer boundary")
            pl = s
            if tr is not None:
                R, T = tr
                bound = [c._replace(Pw=self._apply(tr, c.Pw), exact=None) for c in bound]
                pl = ("plane", R @ s[1] + T, R @ s[2], R @ s[3], None)
                hole3 = [None if c is None else [x._replace(Pw=self._apply(tr, x.Pw), exact=None) for x in c]
                         for c in loops3[1 if outer_given else 0:]]
            else:
                hole3 = loops3[1 if outer_given else 0:]
            surf, outer = self.plane_patch(pl, bound, e.de)
            _, o, e1, e2, _ = pl
            e1 = e1 / np.linalg.norm(e1)
            e2 = e2 - (e2 @ e1) * e1
            e2 = e2 / np.linalg.norm(e2)
            holes = []
            for c in hole3:
                if c is None:
                    self.warn("loop", f"{ctx}: inner loop without a model-space curve ignored")
                    continue
                q = self.sample_pieces(c, e.de) - o
                holes.append(np.stack([q @ e1, q @ e2], axis=1))
            return surf, outer, holes
        if tr is not None:
            s = s._replace(Pw=self._apply(tr, s.Pw), exact=None)
        polys: list[np.ndarray | None] = []
        for k, c2 in enumerate(loops2):
            if c2 is None:
                self.warn("loop", f"{ctx}: trimming loop without a parameter-space curve (BPTR) ignored")
                polys.append(None)
                continue
            q = self.sample_pieces(c2, e.de)[:, :2]
            if s.pmap is not None:
                q = s.pmap(q)
            polys.append(q)
        outer = polys[0] if outer_given else None
        holes = [p for p in polys[1 if outer_given else 0:] if p is not None]
        return s, outer, holes

    # ------------------------------------------------------------------
    def children(self, e: _Entry) -> list[int]:
        """DE pointers of the geometric children of a supported constructor entity."""
        pr = self.params(e)
        t = e.etype
        if t == 102:
            N = pr.int(1, "N", 0)
            return [pr.int(2 + k, "DE", 0) for k in range(max(0, min(N, len(pr.t) - 2)))]
        if t == 120:
            return [pr.int(1, "L", 0), pr.int(2, "C", 0)]
        if t == 122:
            return [pr.int(1, "DE", 0)]
        if t == 108:
            return [pr.int(5, "PTR", 0)]
        if t == 142:
            return [pr.int(2, "SPTR", 0), pr.int(3, "BPTR", 0), pr.int(4, "CPTR", 0)]
        if t == 144:
            n2 = pr.int(3, "N2", 0)
            return [pr.int(1, "PTS", 0), pr.int(4, "PTO", 0)] + [
                pr.int(5 + k, "PTI", 0) for k in range(max(0, min(n2, len(pr.t) - 5)))]
        return []

    def build(self) -> IgesModel:
        model = IgesModel(units=self.units, unit_flag=self.unit_flag, source=self.source)
        referenced: set[int] = set()
        for e in self.entries.values():
            if e.etype in (102, 120, 122, 108, 142, 144):
                referenced.update(self.children(e))
        for e in self.entries.values():
            if e.etype not in _SUPPORTED:
                self.skip(e.etype, "unsupported entity type")
        for de, e in self.entries.items():
            t = e.etype
            if t not in _SUPPORTED or t == 124 or de in referenced:
                continue
            if e.status[2] == 5:  # 2D parametric (use flag 05)
                continue
            try:
                if t in _CURVE_TYPES or t == 142:
                    if e.status[1] in (1, 3):  # physically dependent on an unsupported parent
                        continue
                    for c in self.join(self.curve_pieces(de, f"DE {de}"), de):
                        model.curves.append(self.to_curve(c, de))
                        model.curve_de.append(de)
                elif t == 144:
                    s, outer, holes = self.trimmed(e)
                    model.surfaces.append(self.to_surface(s, de))
                    model.trim_loops.append(outer)
                    model.trim_holes.append(holes)
                    model.surface_de.append(de)
                elif t in _SURFACE_TYPES:
                    s = self.surface(de, f"DE {de}")
                    outer = None
                    if not isinstance(s, _S):
                        s, outer = self.plane_patch(s, s[4], de)
                    model.surfaces.append(self.to_surface(s, de))
                    model.trim_loops.append(outer)
                    model.trim_holes.append([])
                    model.surface_de.append(de)
            except _Unsupported as exc:
                self.skip(t, f"DE {de}: {exc}")
        for t in sorted(self.skipped):
            reasons = self.skip_reasons[t]
            extra = "" if reasons[0] == "unsupported entity type" else f" ({reasons[0]}{' ...' if len(reasons) > 1 else ''})"
            warnings.warn(
                f"{self.source}: skipped {self.skipped[t]} entit{'y' if self.skipped[t] == 1 else 'ies'} "
                f"of IGES type {t}{extra}",
                IgesWarning, stacklevel=3,
            )
        for key, msgs in self.warn_msgs.items():
            more = f" (and {len(msgs) - 1} more)" if len(msgs) > 1 else ""
            warnings.warn(f"{self.source}: {msgs[0]}{more}", IgesWarning, stacklevel=3)
        model.skipped = dict(sorted(self.skipped.items()))
        if not model.curves and not model.surfaces:
            raise IgesError(
                f"{self.source}: no supported curve or surface entity found "
                f"(entity types present: {sorted({e.etype for e in self.entries.values()})}; "
                f"skipped: {model.skipped})"
            )
        return model


def _read_text(path_or_text) -> tuple[str, str]:
    if isinstance(path_or_text, bytes):
        return path_or_text.decode("latin-1"), "<bytes>"
    looks_like_text = (
        isinstance(path_or_text, str)
        and ("\n" in path_or_text or "\r" in path_or_text
             or (len(path_or_text) >= 80 and path_or_text[72:73] in ("S", "G")))
    )
    if isinstance(path_or_text, os.PathLike) or (isinstance(path_or_text, str) and not looks_like_text):
        p = Path(path_or_text)
        try:
            data = p.read_bytes()
        except OSError as exc:
            raise IgesError(f"cannot read IGES file {str(p)!r}: {exc}") from None
        return data.decode("latin-1"), p.name
    if isinstance(path_or_text, str):
        return path_or_text, "<text>"
    raise TypeError(f"read_iges expects a path or the file text, got {type(path_or_text).__name__}")


def read_iges(path_or_text: str | os.PathLike | bytes) -> IgesModel:
    """Read the curves and surfaces of a fixed-format ASCII IGES file as NURBS.

    Args:
        path_or_text: a file path (``str`` without line breaks or
            ``os.PathLike``), or the file contents (``str`` with line breaks,
            or ``bytes``).  Lines may end in LF, CRLF or CR and may lack their
            trailing blanks; numbers may use ``E``/``e``/``D``/``d`` exponents.

    Returns:
        :class:`IgesModel` with NURBS curves ``(n,3)`` control points and
        surfaces ``(nu,nv,3)`` nets, the outer trimming loop per surface as a
        ``(k,2)`` polygon in parameter space (or ``None``), and the counts of
        skipped entities by type.

    Raises:
        IgesError: truncated file, wrong column layout, Terminate counts not
            matching, non-numeric or non-finite values, invalid knot vectors
            or weights, dangling/circular pointers, no supported entity.  The
            message names the line, DE number and entity type.

    Warns:
        IgesWarning: one per skipped entity type (with the count), and for
            recoverable oddities (parameter ranges not matching the knots, ...).
    """
    text, source = _read_text(path_or_text)
    try:
        return _Reader(text, source).build()
    except IgesError:
        raise
    except (ValueError, IndexError, KeyError, ZeroDivisionError, OverflowError, ArithmeticError,
            RecursionError, MemoryError, np.linalg.LinAlgError) as exc:
        if not _WRAP_INTERNAL_ERRORS:
            raise
        raise IgesError(f"{source}: malformed IGES data ({type(exc).__name__}: {exc})") from exc


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
    poly = bool(np.all(W == W[0]))
    toks = ["126", str(n - 1), str(p), "1" if nrm is not None else "0", "1" if closed else "0",
            "1" if poly else "0", "0"]
    toks += [_fmt_real(x) for x in U]
    toks += [_fmt_real(x) for x in W]
    toks += [_fmt_real(x) for x in P.ravel()]
    toks += [_fmt_real(U[p]), _fmt_real(U[n])]
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
    poly = bool(np.all(W == W.flat[0]))
    toks = ["128", str(nu - 1), str(nv - 1), str(p), str(q), "1" if cu else "0", "1" if cv else "0",
            "1" if poly else "0", "0", "0"]
    toks += [_fmt_real(x) for x in U]
    toks += [_fmt_real(x) for x in V]
    toks += [_fmt_real(x) for x in W.T.ravel()]  # W(i,j), i (u) fastest
    toks += [_fmt_real(x) for x in P.transpose(1, 0, 2).ravel()]
    toks += [_fmt_real(U[p]), _fmt_real(U[nu]), _fmt_real(V[q]), _fmt_real(V[nv])]
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
    g_lines = _pack(["1H,", "1H;"] + list(global_params), 72)
    for k, s in enumerate(g_lines, 1):
        out.append(f"{s:<72s}G{k:07d}")
    d_lines, p_lines = [], []
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
