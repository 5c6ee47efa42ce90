"""The held-out suite's machinery: its chi-square band, one case end to end,
and its targets' arithmetic (the full suite is a script:
``python -m diskf_mesh.studies.heldout``)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import scipy.stats

from diskf_mesh.data.scenario import simulate
from diskf_mesh.engine import batch as engine
from diskf_mesh.estimators import NAMES
from diskf_mesh.studies import heldout


@pytest.mark.parametrize("n,seeds", [(2, 20), (4, 20), (3, 10)])
def test_chi2_band_matches_scipy(n, seeds):
    lo, hi = heldout.chi2_band(n, seeds)
    assert lo == pytest.approx(scipy.stats.chi2.ppf(0.025, n * seeds) / seeds, rel=2e-3)
    assert hi == pytest.approx(scipy.stats.chi2.ppf(0.975, n * seeds) / seeds, rel=2e-3)


def test_every_case_builds_and_one_runs():
    cases = heldout.cases()
    labels = [c.label for c in cases]
    assert len(labels) == len(set(labels)) == 235
    assert {c.group for c in cases} == {"inputs", "constant velocity", "3-D state", "p_i = 2", "mixed sensors",
                                        "omega", "R scale", "random geometric", "wrong noise", "bursts",
                                        "rare measurement", "per-channel kinds", "constant acceleration"}
    doc = heldout.run(seeds=2, steps=20, select="S1 ring, white", progress=False)
    (res,) = doc["results"]
    assert set(res["rows"]) == set(NAMES)
    assert not any(r["diverged"] for r in res["rows"].values())
    assert all(0.0 < r["error_ratio"] < heldout.FAR for r in res["rows"].values())
    assert "S1 ring, white" in heldout.markdown(doc)


def test_a_seeds_run_does_not_depend_on_the_seeds_beside_it():
    """Seed 5 simulated and estimated alone, and beside seeds 4 and 6: the
    same trace on every held-out case, and the same estimates of every
    estimator on one case of each kind of model, bit for bit (a stack of
    rows rounds otherwise than one row in BLAS; a case's figures must not
    depend on how many seeds ran with it)."""
    seen = set()
    for case in heldout.cases():
        scn = case.scenario.with_overrides(steps=30)
        alone, beside = simulate(scn, [5]), simulate(scn, [4, 5, 6])
        for f in ("y", "has", "truth_x", "truth_d"):
            assert np.array_equal(getattr(alone, f)[0], getattr(beside, f)[1]), (case.label, f)
        kind = (case.group, scn.G.shape)
        if kind in seen:
            continue
        seen.add(kind)
        for name in NAMES:
            a, b = (_run_or_tick(t, name, scn.params) for t in (alone, beside))
            if isinstance(a, int):  # seed 5 diverged alone: beside others too, at that tick or before
                assert isinstance(b, int) and b <= a, (case.label, name, a, b)
            if isinstance(b, int):  # a batch stops where any of its seeds diverges
                continue
            for f in ("x", "P", "d"):
                assert np.array_equal(getattr(a, f)[0], getattr(b, f)[1]), (case.label, name, f)


def _run_or_tick(trace, name, params):
    """The engine's estimates, or the tick at which it stopped as diverged."""
    try:
        return engine.run(trace, name, params)
    except engine.Diverged as e:
        return e.tick


def test_targets_arithmetic():
    row = lambda v: dict(mae_state=v, mae_input=0.0, nees=2.0, nees_band_share=1.0, diverged=False)  # noqa: E731
    results = [dict(case="a", n=2, rows={"diskf": row(1.0), "diskf-auto": row(1.05), "kcf": row(1.0)}),
               dict(case="b", n=2, rows={"diskf": row(2.0), "diskf-auto": row(1.2), "kcf": row(1.0)})]
    t = heldout.targets(results, 20)
    assert (t["family_within_1pct"], t["auto_within_10pct"], t["auto_nees_in_band"]) == (1, 1, 2)
    assert t["misses"]["family"] == ["b"] and t["misses"]["auto"] == ["b"]
    assert (t["lost_runs"], t["misses"]["lost"]) == (0, [])
    assert (t["auto_diverged"], t["misses"]["diverged"]) == (0, [])
    # a diskf-auto run that diverged misses both of its targets, by name, and is counted
    results.append(dict(case="c", n=2, rows={"diskf": row(1.0), "diskf-auto": dict(row(math.nan), diverged=True),
                                             "kcf": row(1.0)}))
    t = heldout.targets(results, 20)
    assert (t["auto_within_10pct"], t["auto_nees_in_band"], t["auto_nees_cases"]) == (1, 2, 3)
    assert t["misses"]["auto"] == ["b", "c"] and t["misses"]["nees"] == ["c"]
    assert (t["auto_diverged"], t["diverged_runs"], t["misses"]["diverged"]) == (1, 1, ["c: diskf-auto"])
    assert "| runs of `diskf-auto` whose covariance diverged (0) | 1 |" in heldout.markdown(
        dict(seeds=20, steps=None, results=results, targets=t))


def test_error_ratio_is_the_largest_error_over_the_targets_reach(monkeypatch):
    """An estimate equal to the truth but 300 off in one (tick, agent) cell:
    error_ratio is 300 over the target's farthest distance from the origin,
    and the run lost the target once that passes FAR."""
    import numpy as np

    from diskf_mesh.data.scenario import simulate
    from diskf_mesh.engine.batch import Estimates
    from diskf_mesh.studies import experiment

    case = heldout.selected("S1 ring, zero")[0]
    tr = simulate(case.scenario.with_overrides(steps=10), [0])
    S, K, N = tr.has.shape
    n = tr.truth_x.shape[-1]
    x = np.repeat(tr.truth_x[:, :, None, :], N, axis=2).copy()
    x[0, 4, 1, 0] += 300.0
    est = Estimates(x, np.broadcast_to(np.eye(n), (S, K, N, n, n)).copy(), np.zeros((S, K, N, 1)),
                    np.zeros((S, K, N), dtype=bool))
    monkeypatch.setattr(experiment, "run_or_none", lambda *a: est)
    reach = np.linalg.norm(tr.truth_x[..., list(tr.position_dims)], axis=-1).max()
    row = heldout.case_row(tr, "kcf", case.scenario.params)
    assert row["error_ratio"] == pytest.approx(300.0 / reach, rel=1e-12)
    assert heldout.lost(row) == (300.0 / reach > heldout.FAR)


def test_a_run_that_lost_the_target_is_counted_not_hidden():
    """A run whose error passed FAR times the target's reach is named in the
    targets and the table; one stored without error_ratio is not."""
    row = lambda v, ratio=None: dict(mae_state=v, mae_input=0.0, nees=2.0, nees_band_share=1.0,  # noqa: E731
                                     diverged=False, **({} if ratio is None else {"error_ratio": ratio}))
    results = [dict(case="a", n=2, rows={"diskf": row(900.0, 150.0), "diskf-auto": row(1.0, 0.5),
                                         "kcf": row(1.0)})]
    t = heldout.targets(results, 20)
    assert (t["lost_runs"], t["misses"]["lost"]) == (1, ["a: diskf"])
    doc = dict(results=results, targets=t, seeds=20, steps=None)
    assert "lost the target" in heldout.markdown(doc) and "| 1 |" in heldout.markdown(doc).split("lost the target")[1]


def test_model_choice_is_a_distribution_that_finds_no_input():
    from diskf_mesh.data.scenario import load_scenario
    scn = load_scenario("quadrants").with_overrides(topology="all", steps=40)
    t, fam, d = heldout.model_choice(heldout._with_input(scn, heldout.SHIPPED_INPUTS["zero"]))
    total = sum(fam.values())
    assert t.shape == d.shape == (40,)
    assert abs(total - 1).max() < 1e-12
    assert fam["no input"][-1] > 0.9  # no input: the model without one carries the weight


def test_bank_members_are_diskf_auto_models_alone():
    """Each member is diskf-r with one of diskf-auto's bank models: the bank's
    rho and q, and diskf-auto's input prior."""
    from diskf_mesh.estimators import get
    (case,) = [c for c in heldout.cases() if c.label == "R×100 ring, zero"]
    scn = case.scenario
    auto = get("diskf-auto")(scn.model(), scn.sensors(), scn.params)
    members = heldout.bank_members(scn)
    first = auto.a2 == 0  # diskf-r holds the first-order models
    assert [name for name, _ in members] == [b for b, f in zip(auto.bank, first) if f]
    for (_, params), rho, q in zip(members, auto.a1[first], auto.q[first]):
        alone = get("diskf-r")(scn.model(), scn.sensors(), params)
        assert (alone.rho, alone.walk) == (rho, q)
        assert alone.prior == pytest.approx(auto.prior, rel=1e-12)


def test_bank_run_and_summary():
    doc = heldout.run(seeds=1, steps=20, select="S1 none, white", progress=False, bank=True)
    (res,) = doc["results"]
    assert len(res["bank"]) == 8 and all(v > 0 for v in res["bank"].values())
    row = lambda v: dict(mae_state=v, mae_input=0.0, nees=2.0, nees_band_share=1.0, diverged=False)  # noqa: E731
    results = [dict(case="a", n=2, rows={"diskf-auto": row(1.05), "kcf": row(1.0)}, bank={"none": 1.0}),
               dict(case="b", n=2, rows={"diskf-auto": row(2.0), "kcf": row(1.0)}, bank={"none": 1.05, "walk": 3.0}),
               dict(case="c", n=2, rows={"diskf-auto": row(3.0), "kcf": row(1.0)}, bank={"none": 2.0})]
    b = heldout.bank_summary(results)
    assert (b["auto_misses"], b["within"]) == (2, 1)
    assert [(x["case"], x["member"], x["ratio"]) for x in b["rows"]] == [("b", "none", 1.05), ("c", "none", 2.0)]


def test_ticks_since_measured_by_hand():
    import numpy as np
    has = np.array([[[False, True], [True, False], [False, False], [False, True]]])  # (S=1, K=4, N=2)
    assert heldout.ticks_since_measured(has)[0].T.tolist() == [[1, 0, 1, 2], [0, 1, 2, 0]]


def test_by_silence_splits_the_mae_by_ticks_since_measured():
    """Over the agent-ticks of each silence the split's MAE is that of the
    errors there; an all-to-all case whose every agent measures every tick
    (R×0.01 all, zero, made dense) has only silence 0, equal to the run's
    MAE."""
    import numpy as np
    from dataclasses import replace
    (case,) = [c for c in heldout.cases() if c.label == "S1 none, white"]
    out = heldout.by_silence(case, range(1), steps=60)
    assert list(out) == ["diskf-auto"] + [m for m, _ in heldout.bank_members(case.scenario)]
    assert all(len(v) == len(heldout.SILENCES) and all(np.isfinite(v)) for v in out.values())
    # every bin holds agent-ticks here (measured stretches and 30-tick silences): the split agrees with a direct one
    row = heldout.run_case(replace(case, scenario=case.scenario.with_overrides(steps=60)), range(1),
                           names=["diskf-auto"])["diskf-auto"]
    tr = heldout.simulate(case.scenario.with_overrides(steps=60), range(1))
    since = heldout.ticks_since_measured(tr.has)
    weights = [((since >= lo) & (since <= hi)).sum() for lo, hi in heldout.SILENCES]
    assert sum(weights) == since.size
    mixed = sum(w * v for w, v in zip(weights, out["diskf-auto"])) / since.size
    assert mixed == pytest.approx(row["mae_state"], rel=1e-9)


def test_first_seed_runs_the_seeds_it_names():
    """--first-seed 100 --seeds 2: the rows are run_case's on seeds 100 and 101 exactly, and the page says so."""
    case = next(c for c in heldout.cases() if c.label == "S1 ring, white")
    doc = heldout.run(seeds=2, steps=20, select="S1 ring, white", progress=False, first=100)
    want = heldout.run_case(case, [100, 101], 20)
    assert doc["first_seed"] == 100
    assert doc["results"][0]["rows"]["diskf-auto"]["mae_state"] == want["diskf-auto"]["mae_state"]
    assert doc["results"][0]["rows"]["diskf-auto"]["mae_state"] != heldout.run_case(case, [0, 1], 20)["diskf-auto"][
        "mae_state"]
    assert "Seeds 100..101" in heldout.markdown(doc)
    assert heldout.main(["--seeds", "1", "--first-seed", "-1"]) == 2


def test_a_subset_of_estimators_merged_with_a_stored_run_is_that_run(tmp_path):
    """``--estimators A --against FILE``: the estimators run replace theirs,
    every other row is the stored one, the targets are those of the merged
    rows; on the same seeds and ticks the merge of a subset equals the full
    run, row for row."""
    full = heldout.run(seeds=1, steps=20, select=["S1 none, white", "S1 ring, zero"], progress=False)
    part = heldout.run(seeds=1, steps=20, names=["kcf", "diskf-auto"], select=["S1 none, white"], progress=False,
                       jobs=2)
    assert set(part["results"][0]["rows"]) == {"kcf", "diskf-auto"}
    merged = heldout.merge(part, full)
    assert list(merged["results"][0]["rows"]) == list(NAMES)  # the table's columns in the stored order
    same = lambda a, b: json.dumps(a, sort_keys=True, default=float) == json.dumps(b, sort_keys=True, default=float)  # noqa: E731 (NaN)
    want = [r for r in full["results"] if r["case"] == "S1 none, white"]
    assert same(merged["results"], want)
    assert same(merged["targets"], heldout.targets(want, 1))
    edited = json.loads(json.dumps(full, default=float))  # a stored run whose kcf and diskf rows say 999
    for r in edited["results"]:
        r["rows"]["kcf"]["mae_state"] = r["rows"]["diskf"]["mae_state"] = 999.0
    rows = heldout.merge(part, edited)["results"][0]["rows"]
    assert rows["kcf"]["mae_state"] == want[0]["rows"]["kcf"]["mae_state"] != 999.0  # run: the new row
    assert rows["diskf"]["mae_state"] == 999.0                                       # not run: the stored row
    path = tmp_path / "results.json"  # a report's results.json: the document under "heldout", NaN as null
    path.write_text(json.dumps({"heldout": full}, default=float).replace("NaN", "null"))
    back = heldout.stored(path)
    assert back["results"][0]["rows"]["diskf-none"]["mae_input"] != back["results"][0]["rows"]["diskf-none"]["mae_input"]
    assert heldout.merge(part, back)["results"][0]["rows"]["diskf"] == want[0]["rows"]["diskf"]


def test_jobs_give_the_same_document():
    one = heldout.run(seeds=1, steps=15, names=["diskf", "kcf"], select="S1 ring", progress=False)
    two = heldout.run(seeds=1, steps=15, names=["diskf", "kcf"], select="S1 ring", progress=False, jobs=2)
    assert json.dumps(one, default=float) == json.dumps(two, default=float)
    assert len(one["results"]) == 28  # the 11 inputs of Scenario 1 in a ring, and 17 cases of the grown families


def test_against_a_document_of_other_seeds_is_refused_before_running(tmp_path, capsys, monkeypatch):
    doc = heldout.run(seeds=1, steps=20, names=["kcf"], select="S1 none, white", progress=False)
    path = tmp_path / "h.json"
    path.write_text(json.dumps(doc, default=float))
    with pytest.raises(heldout.Mismatch, match="seeds = 1, this run 2"):
        heldout.merge(dict(doc, seeds=2), doc)

    def ran(*a, **k):
        raise AssertionError("the suite ran before the stored document was checked")

    monkeypatch.setattr(heldout, "run", ran)
    monkeypatch.setattr(heldout, "choice_figure", ran)
    argv = ["--estimators", "kcf", "--against", str(path), "--ticks", "20", "--select", "S1 none, white"]
    assert heldout.main(argv + ["--seeds", "2"]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    assert heldout.main(argv + ["--seeds", "1", "--select", "S1 all, white"]) == 2  # a case it does not hold
    assert "no case 'S1 all, white'" in capsys.readouterr().err
    assert heldout.main(["--estimators", "nope"]) == 2
    assert heldout.main(["--against", str(tmp_path / "missing.json")]) == 2
    assert heldout.main(argv + ["--seeds", "1", "--figure", str(tmp_path / "f.png"), "--first-seed", "3"]) == 2


def test_a_world_noisier_than_told_bursts_and_loses_measurements():
    """The trace holds the stated model and sensors; its measurements the
    world's noise: x 10 in covariance, x 30 in a burst, a fifth arriving."""
    import numpy as np

    from diskf_mesh.data.scenario import load_scenario

    scn = load_scenario("quadrants").with_overrides(steps=200)
    seeds = range(10)

    def residual_var(world):
        scn_, tr = heldout.Case("x", "x", scn, world).simulate(seeds)
        e = tr.y[..., 0] - np.einsum("in,bkn->bki", tr.sensors.H[:, 0], tr.truth_x)
        return tr, float((e[tr.has] ** 2).mean() / 2.0)  # Scenario 1's R is 2

    base, v1 = residual_var(None)
    tr10, v10 = residual_var(heldout.World(R=10.0))
    assert 0.9 < v1 < 1.1 and 9.0 < v10 < 11.0
    assert np.array_equal(tr10.sensors.R, base.sensors.R) and np.array_equal(tr10.model.Q, base.model.Q)
    _, vb = residual_var(heldout.BURSTS)  # about a fifth of the ticks in a burst: 1 + 0.18 x 29
    assert 4.0 < vb < 8.0
    rare, _ = residual_var(heldout.RARE)
    assert 0.15 < rare.has.sum() / base.has.sum() < 0.25 and not (rare.has & ~base.has).any()
    assert (rare.y[~rare.has] == 0).all()


def test_channels_draw_each_channel_of_its_own_kind():
    (case,) = [c for c in heldout.cases() if c.label == "m=2 ring, step | white"]
    _, tr = case.simulate([3], 40)
    d = tr.truth_d[0]
    assert (d[:10, 0] == 0).all() and (d[10:, 0] == 10).all() and 1.5 < d[:, 1].std() < 4.5
