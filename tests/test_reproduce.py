"""`dscjax reproduce` (dscjax/reproduce.py, dscjax/cli/reproduce.py, dscjax/complexity.py):
every file is written, the summary's numbers agree with independent computations, and the
pieces (hysteresis loops, growth fits, equation counts) match their references."""

import json
import math
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference_metrics import l2, linf
from test_hysteresis_family import bouc_wen_reference

import dscjax
from dscjax.cli.main import main
from dscjax.config import hysteresis_example
from dscjax.hysteresis import closed_form
from dscjax.reproduce import complexity, sampling
from dscjax.reproduce.figures import FIGURES
from dscjax.reproduce.runs import FAMILY, METRIC_FIELDS, family_loops

T_SHORT = 2.0


def _rc():
    import matplotlib

    return {k: repr(v) for k, v in dict.items(matplotlib.rcParams)}


@pytest.fixture(scope="module")
def reproduced(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper")
    rc, t0 = _rc(), time.perf_counter()
    code = main(["reproduce", "--out", str(out), "--t-final", str(T_SHORT), "--dpi", "40",
                 "--complexity", "--orders", "2-3", "--repeats", "1"])
    elapsed = time.perf_counter() - t0
    assert code == 0
    assert _rc() == rc  # the figures' style is applied with rc_context, never globally
    summary = json.loads((out / "summary.json").read_text())
    return out, summary | {"_elapsed": elapsed}


def test_writes_every_file(reproduced):
    out, summary = reproduced
    for stem in FIGURES.values():
        path = out / f"{stem}.png"
        assert path.is_file() and path.stat().st_size > 1000, stem
    for name in ("summary.json", "summary.md", "complexity.json"):
        assert (out / name).is_file()
    md = (out / "summary.md").read_text()
    assert "| claim | the paper shows | we measured | holds in our run |" in md
    assert set(summary["figures"]) == set(FIGURES)


def test_figs_3_and_4_have_a_panel_after_the_first_second(reproduced):
    # the initial peak (u ~ 6, w ~ 8 within 0.1 s) set the scale of the whole figure: a
    # second panel shows t >= 1 s, so both figures are two panels tall
    import matplotlib.image

    out, _ = reproduced
    for key in ("fig3", "fig4"):
        h, w = matplotlib.image.imread(out / f"{FIGURES[key]}.png").shape[:2]
        assert h > 0.8 * w, (key, h, w)


def test_summary_fields_are_finite(reproduced):
    _, summary = reproduced
    assert summary["t_final"] == T_SHORT and summary["window_start"] == 1.0
    assert set(summary["runs"]) == {"dsc", "dsc_no_dhat", "dsc_no_dhat_no_zeta", "backstepping"}
    for name, run in summary["runs"].items():
        for field in METRIC_FIELDS:
            assert isinstance(run[field], float) and math.isfinite(run[field]), (name, field)
        assert run["diverged"] is False
        for est in run["estimates"].values():
            assert all(math.isfinite(est[k]) for k in ("min", "max", "final"))
    ids = {c["id"] for c in summary["claims"]}
    assert {"compensation_improves_tracking_no_dhat",
            "compensation_improves_tracking_no_dhat_no_zeta",
            "dsc_and_backstepping_track_alike", "dsc_smaller_control_amplitude",
            "signals_bounded", "dsc_removes_explosion_of_complexity"} <= ids
    for c in summary["claims"]:
        assert isinstance(c["holds"], bool) and c["measured"] and c["paper"] and c["verdict"]
    # the whole study, timed inside the command: less than the call took, more than its parts
    assert summary["complexity"]["wall_time_s"] < summary["wall_time_s"] < summary["_elapsed"]


def test_summary_numbers_match_an_independent_computation(reproduced):
    """The DSC row recomputed from a fresh run with the array-based metric functions (a
    different implementation from the running metrics the summary uses)."""
    _, summary = reproduced
    traj = dscjax.simulate(dscjax.paper_example(), T_SHORT, 1e-3, save_every=1)
    t, e, u, w = (np.asarray(a) for a in (traj.t, traj.e, traj.u, traj.w))
    row = summary["runs"]["dsc"]
    np.testing.assert_allclose(row["linf_error"], float(linf(e)), rtol=1e-12)
    np.testing.assert_allclose(row["linf_error_after_1s"], float(linf(e, t, 1.0)),
                               rtol=1e-12)
    np.testing.assert_allclose(row["l2_error"], float(l2(e, t)), rtol=1e-10)
    np.testing.assert_allclose(row["l2_error_after_1s"], float(l2(e, t, 1.0)),
                               rtol=1e-10)
    np.testing.assert_allclose(row["max_abs_u"], np.max(np.abs(u)), rtol=1e-12)
    np.testing.assert_allclose(row["max_abs_u_after_1s"], np.max(np.abs(u[t >= 1.0])),
                               rtol=1e-12)
    np.testing.assert_allclose(row["max_abs_w"], np.max(np.abs(w)), rtol=1e-12)
    np.testing.assert_allclose(row["tv_u"], np.sum(np.abs(np.diff(u))), rtol=1e-10)
    # The claims are consistent with the rows they are computed from.
    claims = {c["id"]: c for c in summary["claims"]}
    runs = summary["runs"]
    amp = claims["dsc_smaller_control_amplitude"]
    assert amp["holds"] == (runs["dsc"]["max_abs_u"] < runs["backstepping"]["max_abs_u"])
    comp = claims["compensation_improves_tracking_no_dhat_no_zeta"]
    q = runs["dsc_no_dhat_no_zeta"]["l2_error_after_1s"] / runs["dsc"]["l2_error_after_1s"]
    np.testing.assert_allclose(comp["ratio_l2"], q, rtol=1e-12)


def test_sampling_study(reproduced):
    """The figure of the sampled controller: every Ts of the figure, the paper's continuous
    loop (at the finest plant step, 0.1 ms) equal to one `simulate` at that step, first-order
    convergence as Ts -> 0 (one exponential-Euler step of the controller per sample, a
    zero-order hold on u), and the sampled loop at Ts = 2 ms equal to one `simulate` with
    that sample time; at Ts = 0.5 ms (ten plant steps of 0.1 ms to a step of dt, one program
    for every Ts) equal to one `simulate` at dt = 0.1 ms."""
    _, summary = reproduced
    s = summary["sampling"]
    assert s["sample_times"] == list(sampling.SAMPLE_TIMES)
    fine = dscjax.simulate(dscjax.paper_example(), T_SHORT, 1e-4, save_every=10)
    np.testing.assert_allclose(s["paper"]["continuous"],
                               float(fine.metrics["linf_error_window"]), rtol=1e-10)
    # and within RK4's error at dt of the DSC row, computed at dt = 1 ms by another run
    np.testing.assert_allclose(s["paper"]["continuous"],
                               summary["runs"]["dsc"]["linf_error_after_1s"], rtol=1e-3)
    assert 0.8 < s["order"]["order"] < 1.2
    assert s["order"]["sample_times"] == [ts for ts in sampling.SAMPLE_TIMES if ts <= 1e-3]
    traj = dscjax.simulate(dscjax.paper_example(), T_SHORT, 1e-3, sample_time=2e-3)
    i = s["sample_times"].index(2e-3)
    np.testing.assert_allclose(s["paper"]["sampled"][i],
                               float(traj.metrics["linf_error_window"]), rtol=1e-10)
    fine = dscjax.simulate(dscjax.paper_example(), T_SHORT, 1e-4, sample_time=5e-4,
                           save_every=10)
    np.testing.assert_allclose(s["paper"]["sampled"][s["sample_times"].index(5e-4)],
                               float(fine.metrics["linf_error_window"]), rtol=1e-10)
    assert all(isinstance(v, float) for v in s["paper"]["sampled"])
    assert "## The controller sampled at Ts" in (reproduced[0] / "summary.md").read_text()


def test_complexity_rows(reproduced):
    out, _ = reproduced
    cx = json.loads((out / "complexity.json").read_text())
    rows = {(r["controller"], r["n"]): r for r in cx["rows"]}
    assert set(rows) == {(c, n) for c in ("dsc", "backstepping") for n in (2, 3)}
    for r in rows.values():
        assert r["eqns"] > 0 and r["flops"] > 0, r
        # timings are recorded (a duration cannot fail to be > 0, so only their presence)
        assert all(math.isfinite(r[k]) for k in ("trace_s", "compile_s", "eval_s")), r
    # Backstepping's law is larger and grows faster with n than the DSC's.
    for n in (2, 3):
        assert rows[("backstepping", n)]["eqns"] > rows[("dsc", n)]["eqns"]
    growth_b = rows[("backstepping", 3)]["eqns"] / rows[("backstepping", 2)]["eqns"]
    growth_d = rows[("dsc", 3)]["eqns"] / rows[("dsc", 2)]["eqns"]
    assert growth_b > 2.0 > 1.6 > growth_d


def test_fig1_loops_match_the_closed_form():
    """Fig. 1's RK4 loops equal the solution (5)-(6) on the first rising segment of u."""
    _, t, u, w = family_loops(amplitudes=(3.5,), t_final=1.0)["backlash"]
    u, w = u[0], w[0]
    rising = t <= (math.pi / 2) / 2.3
    ref = closed_form(jnp.asarray(u[rising]), 0.0, 0.0, 1.0, 1.432, 0.105, +1)
    np.testing.assert_allclose(w[rising], np.asarray(ref), atol=1e-9)


def test_fig1_is_the_family_backlash_entry():
    """`reproduce` draws Fig. 1 from the family's backlash loops instead of integrating (4)
    twice; both go through `sine_loops`, so they are the paper's loops exactly when the
    family's backlash model is the paper's (4) (its loops' closed form is checked above)."""
    family = hysteresis_example("backlash").hysteresis
    paper = dscjax.paper_example().hysteresis
    assert type(family) is type(paper)
    a, b = jax.tree.leaves(family), jax.tree.leaves(paper)
    assert len(a) == len(b) > 0
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert jax.tree.structure(family) == jax.tree.structure(paper)


def test_fig1_family_loops_meet_closed_forms_at_the_first_peak():
    """The loops of `reproduce`'s Fig. 1 of every model: rising from u = 0 to the peak k = 6.5
    drags every play (r_j < k), so there w = p0 u + sum p_j (gamma_l(u) - r_j) (gamma_l(u) = u
    for P-I); the backlash model follows (5)-(6); Bouc-Wen follows scipy's solution of its
    ODE, and its h stays within its bound."""
    fam = family_loops(amplitudes=(6.5,), t_final=1.0)
    assert tuple(fam) == FAMILY
    for kind, (model, t, u, w) in fam.items():
        k = int(np.argmax(u[0]))
        assert 0 < k < len(t) - 1 and u[0, k] > 6.49
        uk, wk = float(u[0, k]), float(w[0, k])
        tol = 1e-12  # the plays are the exact recursion; backlash (4) is RK4's ODE solution
        if kind == "backlash":
            ref = float(closed_form(jnp.asarray(uk), 0.0, 0.0, 1.0, 1.432, 0.105, +1))
            tol = 1e-6
        elif kind == "bouc_wen":  # scipy DOP853 on the ODE, and h within its bound
            ref = float(bouc_wen_reference(model, 6.5, 2.3, np.asarray(t[:k + 1]))[-1])
            tol = 1e-6
            assert abs(wk - float(model.a) * uk) <= float(model.b * model.h_max())
        else:
            r, p = np.asarray(model.r), np.asarray(model.p)
            g = uk
            if kind == "gpi":
                a, b, c, d = np.asarray(model.envelope_left)
                g = a * np.tanh(b * uk + c) + d
            ref = float(model.p0) * uk + float(np.sum(p * (g - r)))
        assert wk == pytest.approx(ref, rel=tol), kind


def test_growth_fit_recovers_known_laws():
    ns = np.arange(2, 9)
    geo = complexity.fit_growth(ns, 7.0 * 3.0**ns)
    assert geo["ratio_per_order"] == pytest.approx(3.0, rel=1e-12)
    assert geo["r2_geometric"] == pytest.approx(1.0)
    power = complexity.fit_growth(ns, 5.0 * ns**1.5)
    assert power["exponent"] == pytest.approx(1.5, rel=1e-12)
    assert power["r2_power"] > power["r2_geometric"]


def test_count_eqns_inlines_sub_jaxprs():
    def inner(x):
        return jnp.sin(x) * 2.0 + 1.0  # 3 equations

    def outer(x):
        return jax.jit(inner)(x) - x  # the jit's 3 + 1

    assert complexity.count_eqns(jax.make_jaxpr(outer)(1.0).jaxpr) == 4


def test_bad_orders_is_a_usage_error(tmp_path, capsys):
    assert main(["reproduce", "--out", str(tmp_path), "--orders", "1-3"]) == 2
    assert "--orders" in capsys.readouterr().err


def test_bad_theory_orders_name_the_option_typed(tmp_path, capsys):
    assert main(["reproduce", "--out", str(tmp_path), "--theory-orders", "1,3"]) == 2
    err = capsys.readouterr().err
    assert "error: --theory-orders must be orders n >= 2 (got '1,3', which includes n = 1)" in err
    assert "--orders" not in err


def test_complexity_study_resumes_after_interruption(tmp_path, monkeypatch):
    """Each finished measurement is saved at once; a resumed study measures only the rest."""
    calls = []
    real = complexity.measure

    def measure(c, n, **kw):
        if len(calls) == 2:  # the third law is interrupted (Ctrl-C)
            raise KeyboardInterrupt
        calls.append((c, n))
        return real(c, n, **kw)

    monkeypatch.setattr(complexity, "measure", measure)
    path = tmp_path / "complexity_rows.json"
    with pytest.raises(KeyboardInterrupt):
        complexity.study((2, 3), repeats=1, evals=20, log=None, rows_path=path)
    saved = json.loads(path.read_text())
    assert [(r["controller"], r["n"]) for r in saved["rows"]] == [("dsc", 2), ("backstepping", 2)]

    def counted(c, n, **kw):
        calls.append((c, n))
        return real(c, n, **kw)

    calls.clear()
    monkeypatch.setattr(complexity, "measure", counted)
    result = complexity.study((2, 3), repeats=1, evals=20, log=None, rows_path=path,
                              resume=True)
    assert calls == [("dsc", 3), ("backstepping", 3)]  # only the unfinished ones
    kept = {(r["controller"], r["n"]): r for r in saved["rows"]}
    for r in result["rows"][:2]:
        assert r == kept[(r["controller"], r["n"])]
    assert len(json.loads(path.read_text())["rows"]) == 4
    # other settings, or nothing saved: an error, not a silent fresh start
    calls.clear()
    with pytest.raises(dscjax.ConfigError, match=r"other settings \(repeats 1 \(now 2\)\)"):
        complexity.study((2,), repeats=2, evals=20, log=None, rows_path=path, resume=True)
    with pytest.raises(dscjax.ConfigError, match="nothing to resume"):
        complexity.study((2,), repeats=1, evals=20, log=None, rows_path=tmp_path / "no.json",
                         resume=True)
    assert calls == []
