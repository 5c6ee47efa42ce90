"""Fast paths of ``linalg`` and ``engine`` against their general forms."""
from __future__ import annotations

import numpy as np
import pytest

from diskf_mesh import estimators as algorithms
from diskf_mesh.engine import batch as engine
from diskf_mesh.core.linalg import (
    FEW,
    T,
    cholesky,
    congruence,
    congruence_const,
    congruence_each,
    eigvalsh,
    inv_spd,
    inv_spd_cholesky,
    inv_spd_each,
    matmul_left,
    matmul_right,
    matmul_shared,
    mv,
    nbr_sum,
    nbr_sum_pair,
    pair_sum,
    row_sum,
    solve,
    sum_order,
    sym,
    transposed,
)
from diskf_mesh.data.scenario import load_scenario, simulate


def random_spd(rng, shape, n, cond=1e3):
    Qm, _ = np.linalg.qr(rng.standard_normal(shape + (n, n)))
    scale = 10.0 ** rng.uniform(-3, 3, shape)[..., None]
    eig = scale * np.exp(rng.uniform(0, np.log(cond), shape + (n,)))
    return (Qm * eig[..., None, :]) @ np.swapaxes(Qm, -1, -2)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_inv_spd_closed_form_matches_cholesky(n):
    a = random_spd(np.random.default_rng(n), (50, 7), n)
    fast, ref = inv_spd(a), inv_spd_cholesky(a)
    scale = np.abs(ref).max(axis=(-2, -1), keepdims=True)
    assert np.max(np.abs(fast - ref) / scale) < 1e-12
    assert (fast == np.swapaxes(fast, -1, -2)).all()


@pytest.mark.parametrize("bad", [[[1.0, 2.0], [2.0, 1.0]], [[-1.0, 0.0], [0.0, 1.0]], [[0.0]], [[-2.0]]])
def test_inv_spd_rejects_non_positive_definite(bad):
    a = np.asarray(bad)
    with pytest.raises(np.linalg.LinAlgError):
        inv_spd_cholesky(a)
    with pytest.raises(np.linalg.LinAlgError):
        inv_spd(np.stack([np.eye(len(a)), a]))


@pytest.mark.parametrize("n", [1, 2])
def test_inv_spd_propagates_nan_like_cholesky(n):
    a = np.eye(n)
    a[0, 0] = np.nan
    assert np.isnan(inv_spd_cholesky(a)).any() and np.isnan(inv_spd(a)).any()


@pytest.mark.parametrize("cols", [1, 2, 3])
def test_mv_matches_matmul(cols):
    rng = np.random.default_rng(cols)
    a, v = rng.standard_normal((6, 5, 2, cols)), rng.standard_normal((6, 5, cols))
    np.testing.assert_allclose(mv(a, v), (a @ v[..., None])[..., 0], rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_solve_matches_lapack(n):
    rng = np.random.default_rng(10 + n)
    a = random_spd(rng, (40,), n) + rng.standard_normal((40, n, n)) * 0.1  # not symmetric
    b = rng.standard_normal((40, n, 3))
    want = np.linalg.solve(a, b)
    np.testing.assert_allclose(solve(a, b), want, rtol=1e-11, atol=1e-12 * np.abs(want).max())
    with pytest.raises(np.linalg.LinAlgError):
        solve(np.zeros((2, n, n)), b[:2])


@pytest.mark.parametrize("n", [1, 2, 3])
def test_eigvalsh_matches_lapack(n):
    a = random_spd(np.random.default_rng(20 + n), (40,), n)
    want = np.linalg.eigvalsh(a)
    np.testing.assert_allclose(eigvalsh(a), want, rtol=1e-12, atol=1e-13 * np.abs(want).max())


@pytest.mark.parametrize("m", [1, 2])
def test_congruence_is_sym_gt_x_g(m):
    rng = np.random.default_rng(30 + m)
    G, X = rng.standard_normal((3, m)), rng.standard_normal((7, 3, 3))
    np.testing.assert_allclose(congruence(G, X), sym(T(G) @ X @ G), rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("core", [1, 2])
def test_nbr_sum_is_broadcast_sum_and_row_deterministic(core):
    rng = np.random.default_rng(core)
    adj = (rng.random((3, 40, 40)) < 0.3).astype(float) * rng.random((3, 40, 40))
    adj[:, 5] = adj[:, 9]  # receivers 5 and 9 hear the same senders
    x = rng.standard_normal((3, 40) + (2,) * core) * 10.0 ** rng.uniform(-8, 8, (3, 40) + (2,) * core)
    want = (adj.reshape(adj.shape + (1,) * core) * np.expand_dims(x, -core - 2)).sum(axis=-core - 1)
    got = nbr_sum(adj, x, core)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got[:, 5], got[:, 9])


@pytest.mark.parametrize("core", [1, 2])
def test_nbr_sum_batch_innermost_order_is_the_same_sum(core):
    """Many small neighbourhoods (the Table II batch): ``nbr_sum`` runs its
    einsum in Fortran order, and still equals the broadcast sum bit for bit,
    receivers that hear the same senders included."""
    rng = np.random.default_rng(10 + core)
    adj = (rng.random((60, 4, 4)) < 0.6) * rng.random((60, 4, 4))
    adj[:, 2] = adj[:, 0]
    x = rng.standard_normal((60, 4) + (2,) * core) * 10.0 ** rng.uniform(-8, 8, (60, 4) + (2,) * core)
    assert sum_order(x, core) == "F"
    want = (adj.reshape(adj.shape + (1,) * core) * np.expand_dims(x, -core - 2)).sum(axis=-core - 1)
    got = nbr_sum(adj, x, core)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got[:, 2], got[:, 0])
    for b in (1, 7, 33):  # and whatever the batch, as the seeds run alone
        np.testing.assert_array_equal(nbr_sum(adj[:b], x[:b], core), want[:b])


@pytest.mark.parametrize("shape", [(60, 4), (3, 9), (1, 1000), (7,)])
@pytest.mark.parametrize("n", [2, 3])
def test_one_blas_call_equals_stacked_matmul(shape, n):
    rng = np.random.default_rng(n)
    X, A = rng.standard_normal(shape + (n, n)) * 10.0 ** rng.uniform(-6, 6, shape + (n, n)), rng.standard_normal((n, n))
    np.testing.assert_array_equal(matmul_right(X, A), np.matmul(X, A))
    np.testing.assert_array_equal(congruence_const(A, X), np.matmul(np.matmul(A, X), T(A)))


@pytest.mark.parametrize("shape", [(20, 9, 21), (1, 1, 21), (60, 4, 21), (3,)])
@pytest.mark.parametrize("r, k, c", [(2, 2, 2), (2, 4, 4), (4, 2, 2), (3, 3, 1), (1, 2, 2), (2, 1, 3)])
def test_one_blas_call_per_shared_factor_equals_stacked_matmul(shape, r, k, c):
    """A constant left factor (one product for the stack) and a factor
    shared by the M models of an agent (one product per agent) give
    np.matmul's bits."""
    rng = np.random.default_rng(r + 10 * k + 100 * c)
    scaled = lambda s: rng.standard_normal(s) * 10.0 ** rng.uniform(-6, 6, s)  # noqa: E731
    A, X = scaled((r, k)), scaled(shape + (k, c))
    np.testing.assert_array_equal(matmul_left(A, X), np.matmul(A, X))
    L, R = scaled(shape[:-1] + (1, r, k)), scaled(shape[:-1] + (1, c, k))
    np.testing.assert_array_equal(matmul_shared(L, X), np.matmul(L, X))
    np.testing.assert_array_equal(matmul_shared(L, X, R), np.matmul(np.matmul(L, X), R))


@pytest.mark.parametrize("n", [1, 2, 3])
def test_transposed_and_sym(n):
    a = np.random.default_rng(n).standard_normal((6, 4, n, n))
    np.testing.assert_array_equal(transposed(a), np.swapaxes(a, -1, -2))
    assert transposed(a).flags.c_contiguous
    np.testing.assert_array_equal(sym(a), 0.5 * (a + np.swapaxes(a, -1, -2)))


def test_stacked_helpers_equal_one_at_a_time():
    rng = np.random.default_rng(3)
    a, b = random_spd(rng, (6, 4), 2), random_spd(rng, (5,), 2)
    for got, want in zip(inv_spd_each(a, b), (inv_spd(a), inv_spd(b))):
        np.testing.assert_array_equal(got, want)
    for m in (1, 2):
        G, Xs = rng.standard_normal((2, m)), [rng.standard_normal((6, 4, 2, 2)) for _ in range(3)]
        for got, X in zip(congruence_each(G, *Xs), Xs):
            np.testing.assert_array_equal(got, congruence(G, X))


@pytest.mark.parametrize("n", [1, 2, 3])
def test_cholesky_closed_form_is_lapacks_bits(n):
    """1x1 and 2x2 in closed form, a stack or a few at a time: LAPACK's own
    factor bit for bit (reading the lower triangle only), and its errors."""
    rng = np.random.default_rng(60 + n)
    a = random_spd(rng, (300,), n, cond=1e8)
    a[:, 0, -1] += 1.0  # the upper triangle is not read
    want = np.linalg.cholesky(a)
    np.testing.assert_array_equal(cholesky(a), want)
    for i in range(0, 300, 7):
        np.testing.assert_array_equal(cholesky(a[i:i + 3]), want[i:i + 3])
    for bad in (-np.eye(n), np.diag(np.r_[1.0, -1.0, 1.0][:n]) if n > 1 else np.zeros((1, 1))):
        for count in (1, 20):
            with pytest.raises(np.linalg.LinAlgError):
                cholesky(np.repeat(bad[None], count, axis=0))
    nan = np.eye(n)[None].repeat(20, axis=0)
    nan[3, 0, 0] = np.nan
    assert np.array_equal(np.isnan(cholesky(nan)), np.isnan(np.linalg.cholesky(nan)))
    assert np.array_equal(np.isnan(cholesky(nan[3:4])), np.isnan(np.linalg.cholesky(nan[3:4])))


@pytest.mark.parametrize("n", [1, 2])
def test_few_matrices_take_paths_with_the_same_bits(n):
    """A stack of at most ``FEW`` matrices (an agent's batch of one) takes the
    Python-float paths; a large stack the numpy ones: entry for entry the same."""
    rng = np.random.default_rng(40 + n)
    count = 200
    a = random_spd(rng, (count,), n)
    g = rng.standard_normal((count, n, n)) * 10.0 ** rng.uniform(-8, 8, (count, n, n))
    v = rng.standard_normal((count, n)) * 10.0 ** rng.uniform(-8, 8, (count, n))
    A = rng.standard_normal((n, n))
    assert count > FEW
    whole = {
        "inv_spd": inv_spd(a), "sym": sym(g), "solve": solve(g, a), "mv": mv(g, v), "mv_const": mv(A, v),
        "congruence_const": congruence_const(A, a),
    }
    for i in range(0, count, 3):  # one matrix at a time, and a few at once
        for one in (slice(i, i + 1), slice(i, i + 3)):
            few = {
                "inv_spd": inv_spd(a[one][None]), "sym": sym(g[one][None]), "solve": solve(g[one][None], a[one][None]),
                "mv": mv(g[one][None], v[one][None]), "mv_const": mv(A, v[one][None]),
                "congruence_const": congruence_const(A, a[one][None]),
            }
            for name, got in few.items():
                np.testing.assert_array_equal(got[0], whole[name][one], err_msg=name)
    for got, want in zip(inv_spd_each(a[:1], a[1:3]), (inv_spd(a)[:1], inv_spd(a)[1:3])):
        np.testing.assert_array_equal(got, want)


def test_few_matrices_reject_and_propagate_like_numpy():
    with pytest.raises(np.linalg.LinAlgError):
        solve(np.zeros((1, 2, 2)), np.eye(2)[None])
    for n in (1, 2):
        bad = -np.eye(n)[None]
        with pytest.raises(np.linalg.LinAlgError):
            inv_spd(bad)
        nan = np.full((1, n, n), np.nan)
        assert np.isnan(inv_spd(nan)).all() and np.isnan(solve(nan, np.eye(n)[None])).all()


def test_nbr_sum_pair_is_two_nbr_sums():
    rng = np.random.default_rng(5)
    adj, M, v = rng.random((3, 6, 6)), rng.standard_normal((3, 6, 2, 2)), rng.standard_normal((3, 6, 2))
    got_M, got_v = nbr_sum_pair(adj, M, v)
    np.testing.assert_array_equal(got_M, nbr_sum(adj, M, 2))
    np.testing.assert_array_equal(got_v, nbr_sum(adj, v, 1))


@pytest.mark.parametrize("name", algorithms.NAMES)
def test_gathered_neighbours_match_dense(name):
    scn = load_scenario("random-geometric", agents=40).with_overrides(steps=40)
    trace = simulate(scn, [0, 1])
    dense = engine.run(trace, name, neighbours="dense")
    gathered = engine.run(trace, name, neighbours="gather")
    np.testing.assert_array_equal(dense.d_valid, gathered.d_valid)
    for f in ("x", "P", "d"):
        np.testing.assert_allclose(getattr(gathered, f), getattr(dense, f), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", ["diskf", "gdkf"])
def test_run_many_equals_separate_runs(name):
    scn = load_scenario("quadrants").with_overrides(steps=50)
    traces = [simulate(scn.with_overrides(topology=t), [0, 1]) for t in ("all", "ring", "none")]
    for est, tr in zip(engine.run_many(traces, name), traces):
        alone = engine.run(tr, name)
        for f in ("x", "P", "d", "d_valid"):
            np.testing.assert_array_equal(getattr(est, f), getattr(alone, f))


@pytest.mark.parametrize("name", ["diskf", "gdkf"])
def test_seed_chunks_equal_one_batch(name, monkeypatch):
    trace = simulate(load_scenario("random-geometric", agents=40).with_overrides(steps=20), [0, 1, 2])
    whole = engine.run_batch(trace, name)
    monkeypatch.setattr(engine, "TICK_BYTES_MAX", 1)  # one seed per chunk
    assert engine.seeds_per_chunk(trace) == 1
    ticks = []
    chunked = engine.run(trace, name, progress=ticks.append)
    assert ticks == list(range(1, 61))
    for f in ("x", "P", "d", "d_valid"):
        np.testing.assert_array_equal(getattr(chunked, f), getattr(whole, f))


@pytest.mark.parametrize("core", [None, (1,), (1, 1), (2,)])
def test_neighbour_sums_go_sender_by_sender_whatever_the_zeros(core):
    """An agent sums over its J neighbours, the engine over all N agents with
    zero weights: both must add the nonzero terms one by one in sender order
    (numpy's unrolled reductions would not), so that they give the same bits.
    ``core`` None: ``row_sum`` of the weights themselves; a vector core:
    ``pair_sum`` too."""
    rng = np.random.default_rng(7)
    for _ in range(300):
        N = int(rng.integers(2, 20))
        w = np.where(rng.random(N) < 0.4, rng.random(N) * 10.0 ** rng.uniform(-3, 3, N), 0.0)
        nz = np.flatnonzero(w)
        if not len(nz):
            continue
        shape = (N,) + (core or (1,))
        x = rng.standard_normal(shape) * 10.0 ** rng.uniform(-3, 3, (N,) + (1,) * (len(shape) - 1))
        if core is None:
            x = np.ones(shape)
        want = w[nz[0]] * x[nz[0]]
        for j in nz[1:]:
            want = want + w[j] * x[j]
        for ww, xx in ((w, x), (w[nz], x[nz])):  # all N with zeros, and the J nonzero ones
            got = row_sum(ww[None, :])[0] if core is None else nbr_sum(ww[None, :], xx, len(core))[0]
            np.testing.assert_array_equal(got, want[0] if core is None else want)
            if core is not None and len(core) == 1:  # a value per (receiver, sender) pair, one receiver
                np.testing.assert_array_equal(pair_sum(ww[None, :], xx[None])[0], want)


def test_neighbour_sums_do_not_depend_on_the_senders_memory_layout():
    """A value per sender taken out of a wider array by fancy indexing (as
    diskf-auto takes its models out of a message's probabilities) is
    not C-contiguous; einsum's loop order, and so its rounding, would follow
    that layout. The engine's N senders (zeros included) and an agent's J
    then give the same bits only because ``nbr_sum`` sums a contiguous copy."""
    rng = np.random.default_rng(3)
    for _ in range(200):
        N, J = 9, int(rng.integers(2, 6))
        x = np.log(rng.random((1, N, 8)))[..., rng.permutation(8)]  # strides of a fancy index
        assert not x.flags.c_contiguous
        adj = np.zeros((1, N, N))
        sel = np.sort(rng.choice(N, J, replace=False))
        adj[0, 0, sel] = 1.0
        np.testing.assert_array_equal(nbr_sum(adj, x, 1)[0, 0], nbr_sum(np.ones((1, 1, J)), x[:, sel], 1)[0, 0])


@pytest.mark.parametrize("algorithm", algorithms.NAMES)
def test_an_agent_alone_computes_the_engine_bits(algorithm):
    """Every agent as a batch of one (``AgentEstimator``, what an agent process
    runs) in lockstep equals the engine on the same seed bit for bit, dense
    and gathered, on Scenario 2's changing links."""
    from diskf_mesh.mesh.protocol.estimator import lockstep

    scn = load_scenario("dynamic")
    trace = simulate(scn, [0], steps=80)
    x = np.array([[out.x[0, 0] for out in outputs.values()] for _, _, outputs in lockstep(scn, algorithm, trace)])
    for layout in ("dense", "gather"):
        np.testing.assert_array_equal(engine.run(trace, algorithm, scn.params, neighbours=layout).x[0], x)
