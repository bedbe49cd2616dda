import numpy as np
import pytest

import contact


@pytest.fixture(scope="module")
def billet_reference():
    P = contact.billet()
    return P, contact.reference_solve(P)


def rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def test_latin_agrees_with_the_reference_to_1e_8(billet_reference):
    P, R = billet_reference
    L = contact.solve(P, "latin", tol=1e-10, max_iter=3000)
    assert L.converged
    assert rel(L.displacement(), R.u) < 1e-8
    assert rel(L.lam_hat, R.lam) < 1e-8
    assert rel(L.lam, R.lam) < 1e-8
    check = contact.check_laws(P, L.w_hat, L.lam_hat)
    assert check.worst() < 1e-12
    assert check.dissipation > 0
    # the global state is admissible: equilibrium with its own tractions
    u = L.displacement()
    res = (P.K @ u - P.C.T @ (P.L[:, None] * L.lam))[P.free_dofs]
    assert np.abs(res).max() < 1e-9 * np.abs(P.K @ u).max()
    # and satisfies the laws to the level of the indicator: 1e-8 of the traction scale
    # max|lam_N|, which is 1e-8 / mu of the cone's scale mu max|lam_N|
    laws = contact.check_laws(P, L.w, L.lam)
    assert max(laws.penetration, laws.tension, laws.complementarity, laws.slip_direction,
               laws.stick_slip) < 1e-8
    assert laws.cone < 1e-8 / P.mu


def test_latin_p3_reaches_the_reference_solution(billet_reference):
    P, R = billet_reference
    L = contact.solve(P, "latin-p3", tol=1e-6, max_iter=2000)
    assert L.converged
    assert rel(L.displacement(), R.u) < 1e-7
    assert rel(L.lam_hat, R.lam) < 1e-5
    e = L.correction
    assert e.orthogonality_error() < 1e-10
    assert np.all(e.U[P.dirichlet_dofs] == 0)
    assert L.basis_size[-1] == e.rank
    assert np.all(np.diff(L.basis_size) >= 0)  # P3 never drops a mode
    assert L.memory() < (P.n * P.m) * 8


@pytest.fixture(scope="module")
def metric_svd(billet_reference):
    """The reference correction's SVD in the indicator metric."""
    P, R = billet_reference
    lift = contact.solve(P, "latin", max_iter=1).lift.to_dense()
    M = contact.indicator_metric(P)
    return M, R.u - lift, contact.svd_modes(R.u - lift, inner=M)


def test_a_cut_in_the_indicator_metric_changes_the_indicator_by_its_norm(
        billet_reference, metric_svd):
    # truncating the converged correction by d moves the global state along E^- by
    # (C d, -k C d); the indicator against the local stage of the truncated state is
    # then ||d||_M / D to first order (D the indicator's denominator)
    P, R = billet_reference
    M, y, svd = metric_svd
    k = contact.default_search_direction(P)
    Lc = np.concatenate([P.weights, P.weights])
    w = P.C @ R.u
    D = np.sqrt(np.sum(Lc[:, None] * (k * w**2 + R.lam**2 / k)))
    for trunc in (1e-4, 1e-6):
        r = svd.rank(trunc)
        d = y - (svd.space[:, :r] * svd.values[:r]) @ svd.time[:, :r].T
        cut = np.sqrt(np.sum(d * (M @ d)))
        assert cut == pytest.approx(np.linalg.norm(svd.values[r:]), rel=1e-6)
        w_r = w - P.C @ d
        lam_r = R.lam + k * (P.C @ d)
        w_hat, lam_hat = contact.local_stage(w_r, lam_r, k=k, gaps=P.gaps, mu=P.mu)
        eta = contact.indicator(w_r, lam_r, w_hat, lam_hat, Lc, k)
        assert eta == pytest.approx(cut / D, rel=0.02)
        # the relative rule: at most trunc sigma_1 / D per term cut
        assert eta <= trunc * np.sqrt(svd.values.size - r) * svd.values[0] / D


def test_svd_sizes_in_the_metric_by_both_definitions(metric_svd):
    _, y, svd = metric_svd
    sizes = svd.sizes(1e-4)
    assert sizes == {"sigma_ratio": 35, "tail_energy": 52}
    # the Euclidean SVD of y gives other sizes: the norm matters
    assert contact.svd_modes(y).sizes(1e-4) != sizes


def test_latin_pgd_reaches_the_reference_solution(billet_reference, metric_svd):
    P, R = billet_reference
    _, _, svd = metric_svd
    # at eta = 1e-4, LATIN's own contact forces are 4e-3 from the reference; 2e-5 brings
    # them within 1e-3 (contact/README.md)
    L = contact.solve(P, "latin-pgd", tol=2e-5, max_iter=400)
    assert L.converged
    assert rel(L.displacement(), R.u) < 2e-4
    assert rel(L.lam_hat, R.lam) < 1e-3  # contact forces
    e = L.correction
    # the modes are orthonormal in the indicator metric
    assert e.orthogonality_error() < 1e-10
    assert np.all(e.U[P.dirichlet_dofs] == 0)
    # the final expansion is the SVD of the last iterate cut at the truncation (by
    # default tol / 10): its size is the optimal one in the metric at that level, to 10%
    assert e.rank <= 1.1 * svd.rank(2e-6)


def test_latin_pgd_follows_latin_with_a_quasi_optimal_basis(billet_reference, metric_svd):
    P, R = billet_reference
    _, _, svd = metric_svd
    latin = contact.solve(P, "latin", tol=1e-4)
    pgd = contact.solve(P, "latin-pgd", tol=1e-4, max_iter=400)
    assert pgd.converged
    # the reduced global stage departs little from the full one: LATIN's iterations
    assert pgd.iterations <= 1.15 * latin.iterations
    # blocks of modes, a few enrichments (not one pair per iteration)
    assert pgd.info["enrichments"] <= pgd.iterations / 4
    assert pgd.info["pairs_added"] > pgd.info["enrichments"]
    # at the same indicator, as close to the reference as LATIN
    assert rel(pgd.lam_hat, R.lam) < 1.5 * rel(latin.lam_hat, R.lam)
    # trunc = tol / 10 by default; the basis is the optimal size at that level (64
    # exact SVD modes are needed to reach 1e-4, contact/README.md)
    opt = svd.sizes(1e-5)
    assert pgd.correction.rank <= 1.1 * opt["sigma_ratio"]
    assert max(pgd.basis_size) <= 1.25 * opt["sigma_ratio"]  # before the final cut
    assert pgd.info["error_bound"] > 0


def test_pgd_basis_fits_the_svd_while_p3_overshoots(billet_reference, metric_svd):
    P, R = billet_reference
    _, _, opt = metric_svd
    p3 = contact.solve(P, "latin-p3", tol=1e-4, max_iter=400)
    pgd = contact.solve(P, "latin-pgd", tol=1e-4, max_iter=120, trunc=1e-4, block=16)
    n_opt = opt.sizes(1e-4)
    # a fixed truncation at 1e-4 keeps the basis at the optimal size of that level, and
    # the indicator levels off above 1e-4: no fixed basis of that size reaches it
    # (contact/README.md, "What a basis of p modes can reach"); blocks of 16 do not
    # move it enough either
    assert n_opt["sigma_ratio"] <= np.median(pgd.basis_size[-20:]) <= n_opt["tail_energy"]
    assert not pgd.converged and pgd.indicator.min() > 1.1e-4
    assert p3.basis_size[-1] > 1.5 * n_opt["sigma_ratio"]
    # the leading PGD modes are the leading SVD modes in the metric (MAC close to 1)
    M = contact.mac(pgd.correction.U[:, :5], opt.space[:, :5])
    assert np.all(np.diag(M) > 0.9)


def test_latin_p3_touches_nf_sized_vectors_only_for_a_new_pair():
    P = contact.billet(dt=0.02)
    fixed_point = 4
    L = contact.solve(P, "latin-p3", tol=1e-4, max_iter=300, fixed_point=fixed_point)
    work = L.info["nf_columns"]
    assert work.shape == (L.iterations,)
    # the residual norms came from the small projections (no direct recomputation,
    # which only happens below 1e-5 of the right-hand side)
    assert L.info["direct_residuals"] == 0
    # a new pair: the fixed point, CGS2 against W and the projections of one new column
    per_pair = (2 * fixed_point + 13) * L.iterations + 6 * fixed_point + 30
    assert np.all(work <= per_pair)
    # an iteration without a new pair only multiplies small projections
    grew = np.diff(np.concatenate([[0], L.basis_size])) > 0
    assert np.any(~grew)
    assert np.all(work[~grew] == 0)


@pytest.mark.parametrize("enrich", ["departure", "stall"])
def test_latin_pgd_touches_nf_sized_vectors_only_to_enrich(enrich):
    P = contact.billet(dt=0.02)
    L = contact.solve(P, "latin-pgd", tol=1e-4, max_iter=300, enrich=enrich, block=8)
    assert L.converged
    work = L.info["nf_columns"]
    assert work.shape == (L.iterations,)
    history = L.info["compressor_history"]
    # one compressor update per enrichment, and one to finish (the last time functions
    # in the basis, then the converged cut)
    assert [h.kind for h in history[-2:]] == ["add", "finalize"]
    assert all(h.kind == "add" for h in history[:-1])
    assert len(history) == L.info["enrichments"] + 2
    # between enrichments: no nf-sized product ("stall"), or the 4-column sketch of the
    # departure rule (4 solves and their right-hand sides, one product with W, whose
    # columns are at most 3 p / 2 + 2 block + 16)
    assert L.info["enrichments"] < L.iterations / 2
    limit = 0 if enrich == "stall" else 2 * 4 + 3 * int(L.basis_size.max()) // 2 + 32
    assert np.sum(work > limit) <= L.info["enrichments"]


def test_callback_receives_every_iteration_and_can_stop():
    P = contact.billet(dt=0.05)
    seen = []

    def cb(state):
        seen.append(state)
        return state.iteration == 7

    L = contact.solve(P, "latin-p3", tol=1e-12, callback=cb)
    assert L.iterations == 7 and not L.converged
    assert [s.iteration for s in seen] == list(range(1, 8))
    assert np.allclose([s.indicator for s in seen], L.indicator)
    assert seen[-1].basis.shape == (len(P.free_dofs), seen[-1].basis_size)
    assert L.cpu_time.shape == (7,) and np.all(L.cpu_time >= 0)


def test_search_direction_changes_the_path_not_the_solution():
    P = contact.billet(dt=0.05)
    k0 = contact.default_search_direction(P)
    a = contact.solve(P, "latin", tol=1e-10, k=k0)
    b = contact.solve(P, "latin", tol=1e-10, k=0.3 * k0)
    assert a.iterations < b.iterations
    assert rel(a.displacement(), b.displacement()) < 1e-8


def test_default_search_direction_is_E_over_the_depth_behind_the_contact_zone():
    # block 3 x 0.5 on the floor: area 1.5 over a contact length 3, h = 0.5
    P = contact.block(np.array([0.0, -0.01]), nx=6, ny=2, width=3.0, height=0.5, E=200.0)
    assert contact.default_search_direction(P) == pytest.approx(200.0 / 0.5)
    assert contact.solve(P, "latin", max_iter=1).k == pytest.approx(400.0)
    # the billet: h = 8.7 mm, the value the docstrings quote
    B = contact.billet()
    assert B.E / contact.default_search_direction(B) == pytest.approx(8.7, abs=0.05)


def test_max_iter_gives_an_unconverged_result():
    P = contact.billet(dt=0.05)
    L = contact.solve(P, "latin", tol=1e-14, max_iter=3)
    assert not L.converged and L.iterations == 3
    assert L.iterations_to(1e-14) is None
    assert np.isnan(L.cpu_time_to(1e-14))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"method": "newton"}, "`method` must be one of"),
        ({"tol": -1.0}, "`tol` must be a positive number"),
        ({"max_iter": 0}, "`max_iter` must be a positive integer"),
        ({"k": 0.0}, "`k` must be a positive number"),
        ({"enrich_ratio": 2.0}, r"`enrich_ratio` must be in \(0, 1\]"),
        ({"trunc": 1.0}, r"`trunc` must be in \[0, 1\)"),
        ({"fixed_point": 0}, "`fixed_point` must be a positive integer"),
        ({"block": 0}, "`block` must be a positive integer"),
        ({"power": -1}, "`power` must be a non-negative integer"),
        ({"enrich": "often"}, "`enrich` must be one of"),
        ({"enrich_tol": 0.0}, "`enrich_tol` must be a positive number"),
    ],
)
def test_solve_rejects_bad_options(kwargs, match):
    P = contact.billet(dt=0.5)
    with pytest.raises(contact.SolverOptionError, match=match):
        contact.solve(P, **kwargs)


def test_solve_rejects_a_non_problem():
    with pytest.raises(ValueError, match="`problem` must be a contact.Problem"):
        contact.solve("billet")
