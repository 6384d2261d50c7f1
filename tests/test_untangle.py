"""Tests of nagata_snap.smoothing.untangle (the regularised mean-ratio objective and its Newton minimiser)
and of NagataGeometry.project (closest points on the coarse patches, used by sliding)."""

import json
import os
import pathlib
import subprocess
import sys

import mpi4py.MPI as MPI
import numpy as np
import pytest
from scipy.optimize import minimize

import dolfinx.mesh

from nagata_snap import NagataGeometry
from nagata_snap.smoothing import untangle
from nagata_snap.smoothing.quality import inverted_cells
from nagata_snap.mesh.records import Records

RNG = np.random.default_rng(7)


def simplex(d):
    """One reference cell, one distorted copy (nearly flat: the regularisation matters)."""
    xr = RNG.normal(size=(d + 1, d))
    x = xr + 0.3 * RNG.normal(size=xr.shape)
    x[1] = x[0] + 0.02 * (x[1] - x[0])
    return np.arange(d + 1)[None], xr, x


@pytest.mark.parametrize("d", [2, 3])
def test_energy_gradient_and_hessian_match_finite_differences(d):
    cells, xr, x = simplex(d)
    winv = untangle.targets(xr, cells)
    delta, e = 0.05, 1e-6
    _, g, _, H = untangle.energy(x, cells, winv, delta, hessian=True)
    gf = np.zeros_like(x)
    Hf = np.zeros((d + 1, d, d + 1, d))
    for v in range(d + 1):
        for c in range(d):
            xp, xm = x.copy(), x.copy()
            xp[v, c] += e
            xm[v, c] -= e
            fp, gp, _ = untangle.energy(xp, cells, winv, delta)
            fm, gm, _ = untangle.energy(xm, cells, winv, delta)
            gf[v, c] = (fp - fm) / (2 * e)
            Hf[:, :, v, c] = (gp - gm) / (2 * e)
    np.testing.assert_allclose(g, gf, rtol=0, atol=1e-7 * np.abs(g).max())
    np.testing.assert_allclose(H[0], Hf, rtol=0, atol=1e-7 * np.abs(Hf).max())
    # eta = |S|^2 / (d h^(2/d)) with S = A W^-1 = I: 1 for the reference cell itself
    F_ref, _, s_ref = untangle.energy(xr, cells, winv, 1e-12)
    assert F_ref == pytest.approx(1.0, rel=1e-12) and s_ref[0] == pytest.approx(1.0, rel=1e-12)
    # an inverted cell costs more than any valid one, and more the smaller delta
    flip = xr.copy()
    flip[[0, 1]] = flip[[1, 0]]
    assert untangle.energy(flip, cells, winv, 1e-2)[0] > untangle.energy(flip, cells, winv, 1e-1)[0] > 1


@pytest.mark.parametrize("d", [2, 3])
def test_energy_is_invariant_under_vertex_order_and_similarity(d):
    cells, xr, x = simplex(d)
    winv = untangle.targets(xr, cells)
    F0 = untangle.energy(x, cells, winv, 1e-3)[0]
    perm = np.roll(np.arange(d + 1), 1)[None]  # same cell, other vertex order
    assert untangle.energy(x, perm, untangle.targets(xr, perm), 1e-3)[0] == pytest.approx(F0, rel=1e-12)
    Q = np.linalg.qr(RNG.normal(size=(d, d)))[0]
    if np.linalg.det(Q) < 0:
        Q[:, 0] *= -1
    y = 3.0 * x @ Q.T + 1.0  # rotated, scaled, translated: the same shape
    if untangle.energy(x, cells, winv, 1e-3)[2][0] > 0:  # (valid cell: delta -> 0 is harmless)
        assert untangle.energy(y, cells, winv, 1e-12)[0] == pytest.approx(
            untangle.energy(x, cells, winv, 1e-12)[0], rel=1e-9)


def unit_mesh(d, n):
    m = (dolfinx.mesh.create_unit_square(MPI.COMM_SELF, n, n) if d == 2
         else dolfinx.mesh.create_unit_cube(MPI.COMM_SELF, n, n, n))
    x = m.geometry.x[:, :d].copy()
    cells = m.geometry.dofmaps[0]
    inner = ~np.any((x < 1e-12) | (x > 1 - 1e-12), axis=1)
    return x, cells, inner


@pytest.mark.parametrize("d, n", [(2, 8), (3, 4)])
def test_optimise_untangles_scrambled_interior(d, n):
    x_ref, cells, inner = unit_mesh(d, n)
    x = x_ref.copy()
    x[inner] += (0.9 / n) * RNG.uniform(-1, 1, size=x[inner].shape)  # heavily tangled
    winv = untangle.targets(x_ref, cells)
    xp = np.c_[x, np.zeros((len(x), 3 - d))]
    xrp = np.c_[x_ref, np.zeros((len(x), 3 - d))]
    assert inverted_cells(xp, xrp, cells, d).size > 5
    res = untangle.optimise(x, cells, winv, inner, np.full(len(x), 1.0 / n))
    out = np.c_[res.x, np.zeros((len(x), 3 - d))]
    assert inverted_cells(out, xrp, cells, d).size == 0 and res.sigma_min > 0
    np.testing.assert_array_equal(res.x[~inner], x[~inner])  # fixed nodes bit for bit
    # the straight mesh is the optimum of the target-matched objective: back to it
    np.testing.assert_allclose(res.x, x_ref, rtol=0, atol=10 * untangle.DELTA_MIN**2)
    again = untangle.optimise(x, cells, winv, inner, np.full(len(x), 1.0 / n))
    np.testing.assert_array_equal(again.x, res.x)  # deterministic


def test_shrinking_active_set_reaches_the_same_minimum():
    """Few disturbed nodes among many free ones: the final round shrinks onto the nodes still
    moving, and ends where the whole problem's Newton does (within the shrink step)."""
    x_ref, cells, inner = unit_mesh(3, 8)
    x = x_ref.copy()
    centre = np.flatnonzero(inner & (np.linalg.norm(x_ref - 0.5, axis=1) < 0.15))
    x[centre] += (0.5 / 8) * np.random.default_rng(1).uniform(-1, 1, size=x[centre].shape)
    winv = untangle.targets(x_ref, cells)
    scale = np.full(len(x), 1.0 / 8)
    whole = untangle.optimise(x, cells, winv, inner, scale)
    res = untangle.optimise(x, cells, winv, inner, scale, shrink=True)
    assert whole.shrinks == 0 and res.shrinks > 0 and res.converged and whole.converged
    assert res.sigma_min > 0 and abs(res.sigma_min - whole.sigma_min) < 1e-6
    np.testing.assert_array_equal(res.x[~inner], x[~inner])  # fixed nodes bit for bit
    assert np.abs(res.x - whole.x).max() < 10 * untangle.SHRINK_STEP * scale[0]


def test_optimise_keeps_anisotropic_targets():
    """A graded (boundary-layer like) mesh is already optimal: the target is the straight cell."""
    x_ref, cells, inner = unit_mesh(2, 8)
    x_ref = x_ref.copy()
    x_ref[:, 1] = x_ref[:, 1] ** 3  # cells 1e-3 thin next to y = 0
    winv = untangle.targets(x_ref, cells)
    x = x_ref.copy()
    x[inner, 0] += 0.02
    # variables scaled by each node's shortest edge, as in the repair
    e = np.linalg.norm(x_ref[cells[:, [1, 2, 0]]] - x_ref[cells], axis=2)
    scale = np.full(len(x), np.inf)
    for k in range(3):
        np.minimum.at(scale, cells[:, k], e.min(axis=1))
    res = untangle.optimise(x, cells, winv, inner, scale)
    # (the regularised optimum is DELTA_MIN^2 relative away from S = I)
    np.testing.assert_allclose(res.x, x_ref, rtol=0, atol=10 * untangle.DELTA_MIN**2)
    assert np.abs(res.x - x_ref).max() < 1e-3 * scale.min()  # even the thinnest cells


def test_sliding_nodes_move_in_their_tangent_space_only():
    x_ref, cells, inner = unit_mesh(2, 6)
    bottom = np.flatnonzero((x_ref[:, 1] < 1e-12) & (x_ref[:, 0] > 1e-12) & (x_ref[:, 0] < 1 - 1e-12))
    x = x_ref.copy()
    x[bottom[0], 0] += 0.1  # crowd one bottom node towards its neighbour
    winv = untangle.targets(x_ref, cells)
    basis = np.zeros((bottom.size, 2, 1))
    basis[:, 0, 0] = 1.0  # along the bottom side
    res = untangle.optimise(x, cells, winv, inner, np.full(len(x), 1 / 6), slide=bottom, basis=basis)
    np.testing.assert_array_equal(res.x[bottom, 1], x[bottom, 1])  # stayed on y = 0
    assert np.abs(res.x[bottom, 0] - x[bottom, 0]).max() > 1e-3  # and did move along it
    assert np.abs(res.x[bottom, 0] - x[bottom, 0]).max() <= untangle.SLIDE_STEP / 6 + 1e-15


def brute_force_closest(geo, patch, p):
    """Closest point on a triangular patch by SLSQP from a grid of starts (independent of Newton)."""
    def d2(z):
        lam = np.array([1 - z[0], z[0] - z[1], z[1]])
        return np.sum((geo.evaluate([patch], lam[None, None])[0, 0] - p) ** 2)

    best = None
    for e0 in np.linspace(0, 1, 6):
        for z0 in np.linspace(0, e0, 4):
            r = minimize(d2, [e0, z0], bounds=[(0, 1), (0, 1)], method="SLSQP",
                         constraints=[{"type": "ineq", "fun": lambda z: z[0] - z[1]}],
                         options={"ftol": 1e-16, "maxiter": 300})
            if best is None or r.fun < best.fun:
                best = r
    z = best.x
    return geo.evaluate([patch], np.array([[[1 - z[0], z[0] - z[1], z[1]]]]))[0, 0]


def octahedron_sphere():
    t = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return NagataGeometry.from_surface(t, f, normals=lambda x: x)


def test_project_on_nagata_patches_matches_brute_force():
    geo = octahedron_sphere()
    P = geo.num_patches
    lam = RNG.dirichlet([3, 3, 3], size=(P, 3))
    rec = Records(np.arange(P), lam)
    pts = geo.evaluate(np.arange(P), lam) + 0.04 * RNG.normal(size=(P, 3, 3))
    q, new = geo.project(rec, pts)
    np.testing.assert_allclose(geo.evaluate(new.root, new.params), q, rtol=0, atol=1e-15)
    np.testing.assert_allclose(new.params.sum(axis=2), 1.0, rtol=0, atol=1e-14)
    for f in range(P):
        for v in range(3):
            ref = brute_force_closest(geo, f, pts[f, v])
            assert np.linalg.norm(q[f, v] - pts[f, v]) <= np.linalg.norm(ref - pts[f, v]) + 1e-12
            assert np.linalg.norm(q[f, v] - ref) < 1e-6
    # points on the patch project onto themselves
    on, _ = geo.project(rec, geo.evaluate(np.arange(P), lam))
    np.testing.assert_allclose(on, geo.evaluate(np.arange(P), lam), rtol=0, atol=1e-14)


def test_project_keeps_edge_and_corner_slots_on_their_feature():
    geo = octahedron_sphere()
    lam = np.array([[[0.3, 0.7, 0.0], [1.0, 0.0, 0.0], [0.2, 0.5, 0.3]]])  # edge, corner, inside
    rec = Records(np.array([0]), lam)
    pts = geo.evaluate([0], lam) + np.array([[0.05, -0.04, 0.1]])
    q, new = geo.project(rec, pts)
    assert new.params[0, 0, 2] == 0.0 and new.params[0, 0, 0] != 0.3  # moved along its edge only
    np.testing.assert_array_equal(new.params[0, 1], lam[0, 1])  # the corner never moves
    # the edge point is the closest point of the edge curve (brute force along the curve)
    t = np.linspace(0, 1, 200001)
    curve = geo.evaluate([0], np.stack([1 - t, t, 0 * t], axis=1)[None])[0]
    i = np.argmin(np.linalg.norm(curve - pts[0, 0], axis=1))
    assert np.linalg.norm(q[0, 0] - curve[i]) < 1e-5
    # the same vertex seen from the neighbouring patch of that edge gets the same point
    nb = next(p for p in range(1, geo.num_patches) if set(geo.ids[p]) >= set(geo.ids[0, :2]))
    pos = [int(np.flatnonzero(geo.ids[nb] == geo.ids[0, k])[0]) for k in (0, 1)]
    lam_nb = np.zeros((1, 3, 3))
    lam_nb[0, 0, pos] = lam[0, 0, :2]
    lam_nb[0, 1, pos[0]] = lam_nb[0, 2, pos[1]] = 1.0
    q_nb, _ = geo.project(Records(np.array([nb]), lam_nb), np.repeat(pts[:, :1], 3, axis=1))
    np.testing.assert_allclose(q_nb[0, 0], q[0, 0], rtol=0, atol=1e-14)


def test_project_on_curves_2d():
    n = 8
    a = 2 * np.pi * np.arange(n) / n
    pts = np.c_[np.cos(a), np.sin(a)]
    seg = np.c_[np.arange(n), (np.arange(n) + 1) % n]
    geo = NagataGeometry.from_surface(pts, seg, normals=lambda x: x)
    lam = np.array([[[0.5, 0.5], [1.0, 0.0]]] * n)
    rec = Records(np.arange(n), lam)
    target = geo.evaluate(np.arange(n), np.array([[[0.2, 0.8], [1.0, 0.0]]] * n))
    q, new = geo.project(rec, target * 1.01)  # slightly off the curve
    np.testing.assert_allclose(new.params[:, 0], [[0.2, 0.8]] * n, rtol=0, atol=2e-3)
    np.testing.assert_array_equal(new.params[:, 1], lam[:, 1])  # coarse vertices stay
    np.testing.assert_allclose(geo.evaluate(new.root, new.params), q, rtol=0, atol=1e-15)


@pytest.mark.mpi
@pytest.mark.parametrize("nprocs", [2, 3])
def test_distributed_optimise_matches_serial(nprocs):
    """The untangler distributed like the mesh (owned cells, ghost copies from their owners)
    against the serial one on the same problem (``tests/mpi/untangle_mpi.py``): a bent,
    scrambled unit square and cube with inverted cells, ghost modes none and shared_facet,
    and with only the nodes no other process has a copy of moving (the Hessian block-diagonal
    by process: each process factorises its block alone).

    Both converge to valid meshes with the same rounds; the nodes agree to round-off times
    the conditioning of the Newton systems (1e-8 of the size: the energy's minimum is flat
    enough in some directions that round-off moves it by 1e-9 on the square); every ghost
    copy holds its owner's value; the halo's forward and reverse exchanges are checked
    against the index map; a collective sum has the same bits on every process.
    """
    repo = pathlib.Path(__file__).resolve().parents[1]
    mpiexec = pathlib.Path(sys.executable).parent / "mpiexec"
    assert mpiexec.exists(), f"mpiexec not found next to {sys.executable} (the MPI test cannot run)"
    env = dict(os.environ)
    env["PYTHONPATH"] = str(repo) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.run([str(mpiexec), "-n", str(nprocs), sys.executable,
                           str(repo / "tests" / "mpi" / "untangle_mpi.py")],
                          capture_output=True, text=True, timeout=600, env=env, cwd=repo)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "DONE" in proc.stdout
    lines = [json.loads(ln) for ln in proc.stdout.splitlines() if ln.startswith("{")]
    assert len(lines) == 8 and {(o["d"], o["blocks"]) for o in lines} == {
        (2, False), (3, False), (2, True), (3, True)}
    # the final round's shrinking active set: the same set-ups in both runs, and one at least
    shrinking = [o for o in lines if o["shrink"]]
    assert len(shrinking) == 2 and max(o["shrinks"][0] for o in shrinking) > 0
    assert all(o["shrinks"][0] == o["shrinks"][1] for o in lines), lines
    for out in lines:
        assert out["size"] == nprocs
        # moving nodes on process boundaries: the distributed factorisation; none: the
        # block-diagonal solve on every process
        assert out["block_setups"] == (1 if out["blocks"] else 0), out
        assert out["sigma_min_start"] < 0  # cells were inverted
        assert min(out["sigma_min"]) > 0 and out["converged"] == [True, True], out
        assert out["rounds"][0] == out["rounds"][1], out
        assert abs(out["sigma_min"][0] - out["sigma_min"][1]) < 1e-6, out
        assert out["maxdiff"] < 1e-8, out
        assert out["ghosts_ok"] and out["halo_forward"] and out["halo_reverse"], out
        assert out["total_same_everywhere"], out
