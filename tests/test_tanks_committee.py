"""The committee of the hybrid cascaded-tanks study (`residual.combine = "mean"`): a start
is taken out of a multistart's parameters whole, and the committee's scores are those of
the mean of its members' outputs, each member from its own initial state."""

import json
import re
import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import benchmark_or_skip

from oneshot_jax import datasets, metrics
from oneshot_jax.residual import MLP

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from experiments import cascaded_tanks, config  # noqa: E402
from experiments import cascaded_tanks_hybrid as hybrid  # noqa: E402

PHYS = {"k1": 0.046, "k3": 0.052, "k4": 0.053, "c": -1.84, "h1": 14.7, "h2": 11.7, "k5": 0.75}


def _theta(key, k1=PHYS["k1"]):
    net = MLP(
        2,
        2,
        (3,),
        key=key,
        scale=0.03,
        zero_last=False,
        input_offset=np.array([6.0, 5.0]),
        input_scale=np.array([2.0, 2.0]),
    )
    return {**{k: jnp.asarray(v) for k, v in {**PHYS, "k1": k1}.items()}, "r": net}


def test_member_takes_one_start_whole():
    """Start k of stacked parameters whose non-array parts were dropped (as in
    `Starts.theta`) is that start's tree, the activation restored from `like`."""
    a = _theta(jax.random.PRNGKey(0), k1=0.04)
    b = _theta(jax.random.PRNGKey(1), k1=0.05)
    stacked = hybrid._stack([a, b])
    arrays_only = eqx.filter(stacked, eqx.is_array)
    assert arrays_only["r"].activation is None
    for k, want in enumerate((a, b)):
        got = hybrid.member(arrays_only, a, k)
        assert eqx.tree_equal(
            eqx.filter(got, eqx.is_array), eqx.filter(want, eqx.is_array), typematch=True
        )
        x = np.array([5.0, 4.0])
        np.testing.assert_array_equal(got["r"](x), want["r"](x))
    assert float(hybrid.member(arrays_only, a, 1)["k1"]) == 0.05


@pytest.fixture(scope="module")
def setup():
    data = benchmark_or_skip(datasets.load_cascaded_tanks)
    ex = config.TanksHybridConfig(substeps=1, residual=config.Residual(widths=[3]))
    model, _ = hybrid.hybrid_model(data, ex)
    a = (_theta(jax.random.PRNGKey(0)), np.array([9.0, 7.0]))
    b = (_theta(jax.random.PRNGKey(1), k1=0.044), np.array([8.0, 7.5]))
    return data, model, a, b


def test_committee_of_one_model_is_that_model(setup):
    """Two copies of one member score as the member alone (`evaluate`)."""
    data, model, a, _ = setup
    one = hybrid.evaluate(model, *a, data)
    two = hybrid.evaluate_committee(model, [a, a], data)
    for key in ("rmse_estimation_V", "rmse_validation_V"):
        np.testing.assert_allclose(two[key], one[key], rtol=1e-12)
    np.testing.assert_allclose(two["protocol"]["rmse_V"], one["protocol"]["rmse_V"], rtol=1e-12)
    assert two["protocol"]["members_rmse_V"] == [one["protocol"]["rmse_V"]] * 2


def test_committee_averages_the_members_outputs(setup):
    """Two different members: the scores are those of the mean output, each member
    simulated from its own x0 (estimation) or its own head estimate (protocol)."""
    data, model, a, b = setup
    singles = [hybrid.evaluate(model, *m, data) for m in (a, b)]
    out = hybrid.evaluate_committee(model, [a, b], data)
    z_est = [cascaded_tanks.simulate(model, *m, data.u_est) for m in (a, b)]
    want_est = metrics.rmse(data.y_est, (z_est[0] + z_est[1]) / 2)[0]
    np.testing.assert_allclose(out["rmse_estimation_V"], want_est, rtol=1e-12)
    z = (singles[0]["_pred"]["z"] + singles[1]["_pred"]["z"]) / 2
    np.testing.assert_allclose(out["_pred"]["z"], z, rtol=1e-12)
    n = data.test.n
    want = np.sqrt(np.mean((z[n:] - np.asarray(data.test.y)[n:]) ** 2))
    np.testing.assert_allclose(out["protocol"]["rmse_V"], want, rtol=1e-10)
    members = [s["protocol"]["rmse_V"] for s in singles]
    assert out["protocol"]["members_rmse_V"] == members
    assert min(abs(out["protocol"]["rmse_V"] - v) for v in members) > 1e-3


def test_seed_table_with_and_without_committee():
    """The seeds' table has the committee's columns and mean when every row has them,
    and the single model's columns alone otherwise (`residual.combine = "best"`)."""
    from experiments import cascaded_tanks_hybrid_report as report

    rows = [
        {"seed": 0, "rmse_estimation_V": 0.08, "rmse_test_V": 0.2, "iterations": {"adam": 5}},
        {"seed": 1, "rmse_estimation_V": 0.09, "rmse_test_V": 0.3, "iterations": {"adam": 5}},
    ]
    single = "\n".join(report._seeds(rows))
    assert "committee" not in single
    assert "| mean | | **0.2500** | |" in single
    both = [
        {**r, "committee_rmse_estimation_V": 0.07, "committee_rmse_test_V": v}
        for r, v in zip(rows, (0.1, 0.2))
    ]
    table = "\n".join(report._seeds(both))
    assert "| 1 | 0.0900 | 0.3000 | 0.0700 | 0.2000 | Adam 5 |" in table
    assert "| mean | | **0.2500** | | **0.1500** | |" in table
    assert report._committee({}, None, {"refine": "none"}) == []


def test_committee_paragraph_names_every_members_stop():
    """The committee's paragraph gives each member's final loss, stop reason and test
    RMSE, in the members' order."""
    from experiments import cascaded_tanks_hybrid_report as report

    cm = {
        "member_losses": [0.01, 0.02],
        "member_stops": ["converged", "max_steps_reached"],
        "protocol": {"n": 5, "members_rmse_V": [0.2, 0.3]},
    }
    text = "\n".join(report._committee({}, cm, {"refine": "levenberg_marquardt"}))
    assert "Final losses of the members: 0.01, 0.02; their stops: converged, " in text
    assert "max_steps_reached; their protocol test RMSEs alone: 0.2000, 0.3000 V" in text


def test_selection_scores_the_tail_from_its_own_head(setup):
    """The held-out score of `cascaded_tanks_hybrid_select` reads the tail's head only
    for x0: outputs elsewhere in the record leave the prediction unchanged, the head's
    change it."""
    import dataclasses

    from experiments import cascaded_tanks_hybrid_select as select

    data, model, a, _ = setup
    m, n = 1024 - 64, 5
    z = select.tail_prediction(model, *a, data, m, n)
    assert z.shape == (64,)
    y = np.array(data.y_est)
    y[:m] += 0.5
    y[m + n :] -= 0.5
    moved = dataclasses.replace(data, y_est=y)
    np.testing.assert_allclose(select.tail_prediction(model, *a, moved, m, n), z, atol=1e-10)
    y = np.array(data.y_est)
    y[m : m + n] += 0.5
    head = dataclasses.replace(data, y_est=y)
    assert np.max(np.abs(select.tail_prediction(model, *a, head, m, n) - z)) > 1e-3
    want = np.sqrt(np.mean((z[n:] - data.y_est[m + n :]) ** 2))
    assert select.tail_rmse(z, data, m, n) == pytest.approx(want, rel=1e-12)


def test_selection_page_marks_the_lowest_mean():
    from experiments import cascaded_tanks_hybrid_select as select

    scores = {"a": {"single": [0.3, 0.1], "committee": [0.2, 0.25]}, "b": {"single": [0.2, 0.3]}}
    store = select.merge(None, scores, 768, 5, 256, [0, 1], "python x.py", 1.0)
    md = select.markdown(store)
    assert "| a | single | 0.3000 | 0.1000 | **0.2000** | 1 |" in md
    assert "| a | committee | 0.2000 | 0.2500 | 0.2250 | 1 |" in md
    assert "Lowest mean held-out RMSE: a, single (0.2000 V)" in md


def test_selection_merge_replaces_a_rerun_candidate_and_keeps_the_others():
    from experiments import cascaded_tanks_hybrid_select as select

    first = {"a": {"single": [0.3, 0.1]}, "b": {"single": [0.2, 0.3]}}
    store = select.merge(None, first, 768, 5, 256, [0, 1], "python x.py", 10.0)
    rerun = {"a": {"single": [0.4, 0.4], "refine": ["converged (12)", None]}}
    store = select.merge(store, rerun, 768, 5, 256, [0, 1], "python x.py --only a", 3.0)
    assert store["scores"]["a"] == {**rerun["a"], "run": 2}
    assert store["scores"]["b"] == {**first["b"], "run": 1}
    md = select.markdown(store)
    assert "| a | single | 0.4000 | 0.4000 | 0.4000 | 2 |" in md
    assert "| b | single | 0.2000 | 0.3000 | **0.2500** | 1 |" in md
    assert "| a | converged (12) | not recorded |" in md
    assert "2. `python x.py --only a` (3 s): 'a'." in md
    rerun_b = {"b": {"single": [0.5, 0.5]}}
    store = select.merge(store, rerun_b, 768, 5, 256, [0, 1], "python x.py --only b", 2.0)
    assert [r["command"] for r in store["runs"]] == ["python x.py --only a", "python x.py --only b"]
    assert (store["scores"]["a"]["run"], store["scores"]["b"]["run"]) == (1, 2)
    with pytest.raises(ValueError, match="tail 256 and seeds"):
        select.merge(store, rerun, 768, 5, 256, [0, 1, 2], "python x.py", 1.0)


def test_selection_page_compares_the_rows_with_the_physics_alone():
    """The physical stage's held-out score is the candidates' baseline: the page counts
    the rows below it, or says that none is; a later physical row replaces the earlier,
    and a store of another tail is refused."""
    from experiments import cascaded_tanks_hybrid_select as select

    scores = {"a": {"single": [0.3, 0.1], "committee": [0.2, 0.25]}, "b": {"single": [0.2, 0.3]}}
    store = select.merge(None, scores, 768, 5, 256, [0, 1], "python x.py", 1.0)
    assert "physical stage alone" not in select.markdown(store)
    row = {"rmse": 0.21, "command": "python x.py --physical", "wall_s": 9}
    store = select.merge_physical(store, row, 768, 5, 256, [0, 1])
    md = select.markdown(store)
    assert "trained and scored the same way: 0.2100 V; 1 of the 3 rows score lower" in md
    assert "(`python x.py --physical`, 9 s)" in md
    store = select.merge_physical(store, {**row, "rmse": 0.15}, 768, 5, 256, [0, 1])
    assert "0.1500 V; no row scores lower: on this held-out tail the network" in (
        select.markdown(store)
    )
    alone = select.merge_physical(None, row, 768, 5, 256, [0, 1])
    assert "0.2100 V (`python x.py --physical`" in select.markdown(alone)
    with pytest.raises(ValueError, match="tail 256"):
        select.merge_physical(store, row, 700, 5, 324, [0, 1])


def test_selection_page_states_each_runs_conditions():
    """A run's conditions (machine, versions, the cores the process may use) are kept with
    its rows and printed under it; a run stored without them prints none."""
    from experiments import cascaded_tanks_hybrid_select as select

    where = select.run_conditions()
    assert "CPU cores" in where and "jax " in where and "the run may use" in where
    store = select.merge(None, {"a": {"single": [0.3, 0.1]}}, 768, 5, 256, [0, 1], "x", 1.0)
    store = select.merge(store, {"b": {"single": [0.2, 0.3]}}, 768, 5, 256, [0, 1], "y", 2.0, where)
    md = select.markdown(store)
    assert "1. `x` (1 s): 'a'.\n" in md
    assert f"2. `y` (2 s): 'b'. Conditions: {where}\n" in md
    row = {"rmse": 0.21, "command": "z", "wall_s": 9, "conditions": "machine M."}
    md = select.markdown(select.merge_physical(store, row, 768, 5, 256, [0, 1]))
    assert "(`z`, 9 s; machine M)." in md


def test_hybrid_page_says_whether_a_candidate_beat_the_physical_stage():
    """The hybrid page reports the selection's outcome against the physical stage on the
    held-out tail (the candidates' means over the seeds, as the selection page ranks them):
    that none beat it, so that the estimation record alone would keep the physics, or the
    best candidate's score."""
    from experiments import cascaded_tanks_hybrid_report as report

    store = {"physical": {"rmse": 0.19}, "scores": {"a": {"single": [0.2, 0.22], "run": 1}}}
    assert "None of the candidates beats it there (the best 0.2100 V against the physical " in (
        report.selection_verdict(store)
    )
    store["scores"]["b"] = {"committee": [0.15, 0.17], "run": 1}
    assert "The best candidate scores 0.1600 V there" in report.selection_verdict(store)
    assert report.selection_verdict(None) == ""
    assert report.selection_verdict({"scores": store["scores"]}) == ""


def test_the_published_selection_page_is_its_store_rendered():
    """docs/case-studies/cascaded_tanks_hybrid_selection.md is `markdown` of the stored
    runs (experiments/cascaded_tanks_hybrid_selection.json), as `--publish` writes it: a
    hand edit of the page, or text in the store that the script does not write, shows."""
    from experiments import cascaded_tanks_hybrid_select as select

    store = json.loads(select.STORE.read_text())
    assert select.PAGE.read_text() == select.markdown(store)
    for run in store["runs"]:
        assert re.search(r"; the run may use \d+ of them\.$", run["conditions"]), run["conditions"]
