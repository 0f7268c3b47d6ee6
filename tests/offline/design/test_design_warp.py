"""MLS interpolation, sample placement and the thickness warp of a block."""

from __future__ import annotations

import numpy as np
import pytest

from offline.design.mls import mls_matrix, place_samples
from offline.design.warp import block_warp, harmonic_depth
from offline.fem import box_mesh, min_jacobian


def test_mls_reproduces_affine_fields_and_interpolates_smoothly():
    rng = np.random.default_rng(0)
    samples = rng.uniform(0, 1, (12, 2))
    pts = rng.uniform(0, 1, (50, 2))
    Phi = mls_matrix(pts, samples, width=0.4)
    a = np.array([0.3, -1.2, 2.0])
    h = a[0] + samples @ a[1:]
    assert np.allclose(Phi @ h, a[0] + pts @ a[1:], atol=1e-12)
    assert np.allclose(Phi.sum(axis=1), 1.0)
    # a non-affine field is not reproduced exactly (the kernel smooths)
    hq = samples[:, 0] ** 2
    assert np.abs(Phi @ hq - pts[:, 0] ** 2).max() > 1e-4


def test_mls_refuses_too_narrow_kernel_and_bad_input():
    samples = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    with pytest.raises(ValueError, match="ill-conditioned"):
        mls_matrix(np.array([[10.0, 10.0]]), samples, width=0.05)
    with pytest.raises(ValueError, match="width"):
        mls_matrix(samples, samples, width=0.0)
    with pytest.raises(ValueError, match="at least 3"):
        mls_matrix(samples, samples[:2], width=1.0)


def test_samples_are_denser_where_the_density_map_is_larger():
    g = np.linspace(0, 1, 41)
    cand = np.array(np.meshgrid(g, g)).reshape(2, -1).T
    idx = place_samples(cand, lambda p: np.where(p[:, 0] < 0.5, 9.0, 1.0), 40)
    assert len(np.unique(idx)) == 40
    left = np.sum(cand[idx, 0] < 0.5)
    assert left >= 2 * (40 - left)
    with pytest.raises(ValueError, match="density"):
        place_samples(cand, np.zeros(len(cand)), 5)


def test_block_warp_is_linear_keeps_outer_surface_and_attachments():
    mesh = box_mesh((0.04, 0.02, 0.006), (8, 4, 3))
    warp = block_warp(mesh, n_samples=8)
    assert np.allclose(warp.rest_positions(warp.h_ref), mesh.nodes, atol=1e-15)
    rng = np.random.default_rng(1)
    h1 = warp.h_ref * (1 + 0.2 * rng.uniform(-1, 1, 8))
    h2 = warp.h_ref * (1 + 0.2 * rng.uniform(-1, 1, 8))
    X1, X2, Xm = warp.rest_positions(h1), warp.rest_positions(h2), warp.rest_positions(0.5 * (h1 + h2))
    assert np.allclose(Xm, 0.5 * (X1 + X2), atol=1e-15)
    assert np.allclose(X1 - mesh.nodes, (warp.D @ (h1 - warp.h_ref)).reshape(-1, 3))
    top = mesh.node_sets["z1"]
    assert np.array_equal(X1[top], np.asarray(mesh.nodes)[top])
    for name in ("x0", "x1"):
        idx = mesh.node_sets[name]
        assert np.array_equal(X1[idx], np.asarray(mesh.nodes)[idx])
    assert np.allclose(X1[:, :2], np.asarray(mesh.nodes)[:, :2])  # moves only through the thickness
    assert min_jacobian(mesh, X1) > 0
    # inner-surface thickness at a free node equals the MLS height there
    inner = np.setdiff1d(mesh.node_sets["z0"], np.r_[mesh.node_sets["x0"], mesh.node_sets["x1"]])
    Phi = mls_matrix(np.asarray(mesh.nodes)[inner, :2], warp.samples_uv, warp.width)
    assert np.allclose(0.006 - X1[inner, 2], Phi @ h1, atol=1e-12)
    with pytest.raises(ValueError, match="8 finite"):
        warp.rest_positions(np.ones(3))


def test_harmonic_depth_runs_from_outer_to_inner():
    mesh = box_mesh((0.02, 0.02, 0.008), (4, 4, 4))
    t = harmonic_depth(mesh, mesh.node_sets["z1"], mesh.node_sets["z0"])
    assert np.all(t[mesh.node_sets["z1"]] == 0) and np.all(t[mesh.node_sets["z0"]] == 1)
    z = np.asarray(mesh.nodes)[:, 2]
    mid = np.flatnonzero(np.isclose(z, 0.004))
    assert np.all((t[mid] > 0.3) & (t[mid] < 0.7))


def test_harmonic_depth_on_quadratic_tets_interpolates_mid_edge_nodes():
    from offline.fem import to_quadratic

    lin = box_mesh((0.02, 0.02, 0.008), (3, 3, 2))
    quad = to_quadratic(lin)
    t1 = harmonic_depth(lin, lin.node_sets["z1"], lin.node_sets["z0"], lin.node_sets["x0"])
    t2 = harmonic_depth(quad, quad.node_sets["z1"], quad.node_sets["z0"], quad.node_sets["x0"])
    assert np.allclose(t2[:lin.n_nodes], t1)
    assert np.all(t2[quad.node_sets["z0"][~np.isin(quad.node_sets["z0"], quad.node_sets["x0"])]] == 1)
    assert np.all(t2[quad.node_sets["x0"]] == 0) and np.all(t2[quad.node_sets["z1"]] == 0)
    from offline.fem.mesh import QUADRATIC_EDGES

    tets = np.asarray(quad.tets)
    ends = tets[:, :4][:, QUADRATIC_EDGES]
    mids = tets[:, 4:]
    inner_mid = ~np.isin(mids, np.r_[quad.node_sets["z0"], quad.node_sets["z1"], quad.node_sets["x0"]])
    assert inner_mid.any()
    assert np.allclose(t2[mids][inner_mid], 0.5 * (t2[ends[..., 0]] + t2[ends[..., 1]])[inner_mid])
    # the warp keeps every edge straight: mid-edge nodes stay at their edge's midpoint
    warp = block_warp(quad, n_samples=6)
    rng = np.random.default_rng(0)
    X = warp.rest_positions(warp.h_ref * (1 + 0.25 * rng.uniform(-1, 1, 6)))
    assert np.allclose(X[mids], 0.5 * (X[ends[..., 0]] + X[ends[..., 1]]), atol=1e-15)
    assert min_jacobian(quad, X) > 0


def test_strain_density_places_samples_where_the_block_deforms():
    from offline.design.warp import strain_density
    from offline.fem import neo_hookean, rigid_transform_dirichlet, solve_static

    mesh = box_mesh((0.04, 0.01, 0.004), (16, 4, 2))
    X = np.asarray(mesh.nodes)
    # pull only a patch of the bottom at the x1 end sideways: strain concentrates near x1
    patch = np.flatnonzero((X[:, 0] > 0.03) & (X[:, 2] < 1e-9))
    mesh = mesh.with_node_sets(patch=patch)
    T = np.eye(4)
    T[0, 3] = 0.004
    bc = rigid_transform_dirichlet(mesh, {"patch": T}, fixed_sets=("x0",))
    x = solve_static(mesh, neo_hookean(3e4, 3e5), bc).x
    rho = strain_density(mesh, [x])
    assert rho.min() >= 0.2 and rho.max() == pytest.approx(1.2)
    inner = np.asarray(mesh.node_sets["z0"])

    def rho_at(warp):  # density at the inner-surface node under each sample
        d = np.linalg.norm(X[inner, None, :2] - warp.samples_uv[None], axis=2)
        return rho[inner[np.argmin(d, axis=0)]]

    dense = block_warp(mesh, n_samples=12, density=rho, locked_sets=("x0",))
    uniform = block_warp(mesh, n_samples=12, locked_sets=("x0",))
    assert rho_at(dense).mean() > 1.05 * rho_at(uniform).mean()
    with pytest.raises(ValueError, match="one value per node"):
        block_warp(mesh, n_samples=4, density=np.ones(3))
