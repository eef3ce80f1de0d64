"""The tune report's verdicts against independent computations: the error against the
config's reference where the controller tracks a shifted one (init = "linf"), where the effort
bounds are measured (a start transient), the constraints' elasticities against central
differences, and start gains that diverge (exit 3, which run and when).

Short horizons (0.5-2 s), one plant, no held-out batch where the test does not need it; the
problem with x1(0) = 0.2 has the structure of test_tuning_loop's run (2 s, controller.k, the
sampled loop and its second discretisation), so their compiled programs are shared.
"""

import contextlib
import io
import json
from types import SimpleNamespace

import numpy as np
import pytest

import dscjax
import tuning
from dscjax import params
from dscjax.runspec import RunSpec
from tuning import elasticity, report, report_md


def _cli(run_with_config, directory, toml, *argv):
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code, out = run_with_config(directory, toml, "tune", "--quiet", *argv)
    return code, out, stdout.getvalue(), stderr.getvalue()


def _numpy_errors(setup, spec, t0):
    """(L-inf of x_1 - y_r on t >= t0, on the whole horizon) against the config's y_r (a
    sine: numpy's own), from a trajectory with every step saved."""
    tr = dscjax.simulate(setup, spec=spec.replace(save_every=1, refine=0))
    t, y = np.asarray(tr.t), np.asarray(tr.x)[:, 0]
    ref = setup.reference
    yr = (float(ref.amplitude) * np.sin(float(ref.frequency) * t + float(ref.phase))
          + float(ref.offset))
    e = np.abs(y - yr)
    return float(np.max(e[t >= t0])), float(np.max(e)), tr


SHIFTED = """
[simulation]
t_final = 1.5

[plant]
x0 = [2.0, 0.1]

[controller]
init = "linf"

[tuning]
params = ["controller.k"]

[tuning.objective]
sampled_weight = 0.0

[tuning.optimizer]
name = "cma"
steps = 1

[tuning.heldout]
batch = 0
"""


def test_errors_are_reported_against_the_config_reference_beside_the_shifted_one(
        tmp_path, run_with_config):
    """Issue 38 item 4: with init = "linf" and x0 = (2, 0.1) the controller tracks y_r moved
    to start at x_1(0); the tuner keeps that error, and the console, report.md and report.json
    give the error against the config's y_r beside it, each labelled: on [1, 1.5] s and at
    t = 0, where |y - y_r| = 2 - y_r(0)."""
    code, out, stdout, stderr = _cli(run_with_config, tmp_path, SHIFTED, "--no-plot")
    assert code == 0, stderr
    rep = json.loads((out / "report.json").read_text())
    setup, _ = dscjax.config.from_dict({"plant": {"x0": [2.0, 0.1]},
                                        "controller": {"init": "linf"}},
                                       base=dscjax.paper_example())
    spec = RunSpec.make(1.5, 1e-3, sample_time=1e-3)
    best = json.loads((out / "best.json").read_text())["values"]["controller.k"]
    figures = {}
    for tag, s in (("start", setup),
                   ("tuned", params.set(setup, "controller.k", np.array(best)))):
        window, whole, tr = _numpy_errors(s, spec, 1.0)
        nom = rep["nominal"][tag]
        assert nom["user_linf_error_window"] == pytest.approx(window, rel=1e-9)
        assert nom["user_linf_error"] == pytest.approx(whole, rel=1e-9)
        # the figure tuned: against the shifted reference (trajectory.e)
        shifted = float(np.max(np.abs(np.asarray(tr.e))[np.asarray(tr.t) >= 1.0]))
        assert nom["linf_error_window"] == pytest.approx(shifted, rel=1e-9)
        figures[tag] = (window, shifted)
    # the point: they differ, by the reference's offset still there at t = 1 s
    assert figures["start"][0] > 10 * figures["start"][1]
    assert rep["nominal"]["start"]["user_linf_error"] == pytest.approx(
        2.0 - float(setup.reference(0.0)), rel=1e-12)
    (w0, s0), (w1, s1) = figures["start"], figures["tuned"]
    assert (f"start gains: L-inf error on [t0, T] against the shifted y_r the controller tracks "
            f"(tuned) {s0:.4g}, L-inf error on [t0, T] against the config's y_r {w0:.4g}, "
            ) in stderr
    assert (f"nominal plant, L-inf error on [t0, T] against the shifted y_r the controller "
            f"tracks (tuned): {s0:.4g} -> {s1:.4g}") in stdout
    assert f"nominal plant, L-inf error on [t0, T] against the config's y_r: {w0:.4g} -> " \
           f"{w1:.4g}" in stdout
    md = (out / "report.md").read_text()
    assert (f"| L-inf error on [t0, T] against the config's y_r | {w0:.4g} | {w1:.4g} |"
            in md)
    assert (f"| L-inf error on [t0, T] against the shifted y_r the controller tracks (tuned) "
            f"| {s0:.4g} | {s1:.4g} |") in md
    assert "against the reference the controller tracks" in rep["problem"]


@pytest.fixture(scope="module")
def transient():
    """The problem of test_tuning_loop's run (2 s, controller.k, sampled at 1 ms, the second
    discretisation) from x(0) = (0.2, 0): a start transient of max|u| ~ 120 (issue 38 item
    5); its nominal figures at the start gains. Without the delayed loop: from this start it
    chatters, and the tangents of a chattering loop are not the slopes of its figures."""
    setup = params.set(dscjax.paper_example(), "plant.x0", np.array([0.2, 0.0]))
    cfg = tuning.TuningConfig(params=("controller.k",), heldout=tuning.BatchSpec(batch=0),
                              objective=tuning.ObjectiveSpec(delay_samples=0))
    problem = tuning.build_problem(setup, RunSpec.make(2.0, 1e-3, sample_time=1e-3), cfg)
    ev = report.evaluate(problem, problem.z0, problem.z0)
    nom = {tag: {k: float(np.asarray(v)) for k, v in ev["nominal"][tag].items()}
           for tag in ("start", "tuned")}
    return problem, nom


def test_the_report_says_where_the_effort_bounds_are_measured(transient):
    """Issue 38 item 5: the start's max|u| (the bound) is its transient's, at t < 0.1 s, many
    times its peak on the window; the report states that the bounds are measured on [0, T]
    and gives the effort on the window [1, 2] s beside them (numpy on the trajectory)."""
    problem, nom = transient
    tr = dscjax.simulate(problem.setup, spec=problem.objective.sim.replace(save_every=1))
    t, u = np.asarray(tr.t), np.asarray(tr.u)
    win = t >= 1.0
    peak, peak_win = np.max(np.abs(u)), np.max(np.abs(u[win]))
    tv_win = np.sum(np.abs(np.diff(u[win])))
    assert t[np.argmax(np.abs(u))] < 0.1 and peak > 50 * peak_win
    sc = problem.objective.scales
    assert sc.u_max == pytest.approx(peak, rel=1e-12)
    assert sc.start["max_abs_u_window"] == pytest.approx(peak_win, rel=1e-12)
    assert sc.start["tv_u_window"] == pytest.approx(tv_win, rel=1e-9)
    text = report_md.effort_span({"nominal": nom})
    assert text.startswith("The effort bounds are measured over the whole horizon [0, T], "
                           "the start-up transient included")
    assert (f"the start gains use max|u| {peak_win:.4g} and TV(u) {tv_win:.4g}") in text


def test_constraint_elasticities_match_central_differences(transient):
    """Issue 38 item 3: d ln r / d ln k_i of every constraint (max|u|, TV(u), the check
    loop's: the other discretisation; its L-inf over the first's) by forward mode, against
    central differences of the loops' exact figures in
    float64; the start sits on its max|u| bound (margin 0), so a 1 % change of k_1 breaks it:
    fragile, and the warning says so."""
    problem, nom = transient
    z0 = problem.z0
    checks = report.constraint_checks(problem.objective.scales, nom["start"],
                                      problem.objective.checks)
    sens = elasticity.constraints(problem, z0, checks)
    obj = problem.objective.program()

    def per_plant(z, overrides):  # the report's own compiled program
        return report._per_plant(obj, z, overrides)

    def ratio(m, key):  # value / bound, bounds fixed but the check loops' L-inf's
        return (m[key] / m["linf_error_window"]
                if key in ("sampled_linf_window", "delayed_linf_window") else m[key])

    h = 1e-6
    names = [p.name for p in problem.selection.columns(problem.setup)]
    assert names == ["controller.k[0]", "controller.k[1]"]
    at = []
    for j in range(2):
        for sign in (1, -1):
            z = {"controller.k": z0["controller.k"].at[j].add(sign * h)}
            at.append({k: float(np.asarray(v)) for k, v in per_plant(z, {}).items()})
    assert [r["key"] for r in sens["rows"]] == ["max_abs_u", "tv_u", "sampled_linf_window",
                                                "sampled_max_abs_u", "sampled_tv_u"]
    for row in sens["rows"]:
        for j, name in enumerate(names):
            plus, minus = ratio(at[2 * j], row["key"]), ratio(at[2 * j + 1], row["key"])
            fd = (np.log(plus) - np.log(minus)) / (2 * h)
            assert row["elasticity"][name] == pytest.approx(fd, rel=1e-4, abs=1e-6), (
                row["name"], name)
    on_bound = sens["rows"][0]
    assert on_bound["name"] == "max|u|" and abs(on_bound["relative_margin"]) < 1e-12
    assert "controller.k[0]" in on_bound["fragile"]
    # the others have room: none of their elasticities x 1 % reaches their margin
    for row in sens["rows"][1:]:
        r = row["value"] / row["bound"]
        assert row["fragile"] == [n for n, e in row["elasticity"].items()
                                  if r * (1 + 0.01 * abs(e)) > 1]
    e0 = on_bound["elasticity"]["controller.k[0]"]
    assert elasticity.warning(sens).startswith(
        f"a 1 % change of one tuned number breaks a constraint (to first order, nominal "
        f"plant): max|u| (margin {100 * on_bound['relative_margin']:.3g} % of its bound) by "
        f"controller.k[0] (elasticity {e0:.3g})")


DIVERGES = """
[simulation]
t_final = 0.5

[controller]
k = [60.0, 60.0]

[tuning]
params = ["controller.k"]
"""


def test_start_gains_that_diverge_exit_3_with_which_run_and_when(tmp_path, run_with_config):
    """Issue 38 item 7: a start that diverges is a divergence (exit 3, README's convention),
    one line naming the run (the nominal plant, the loop tuned) and when, as `simulate`
    finds it; no traceback."""
    code, _, stdout, stderr = _cli(run_with_config, tmp_path, DIVERGES)
    setup = params.set(dscjax.paper_example(), "controller.k", np.array([60.0, 60.0]))
    tr = dscjax.simulate(setup, 0.5, 1e-3, sample_time=1e-3, refine=0, throw=False)
    assert bool(tr.diverged)
    assert code == 3
    assert stderr.strip().splitlines()[-1] == (
        "dscjax tune: simulation diverged: the start gains diverge on the nominal plant in "
        "the loop tuned (the controller sampled every Ts = 0.001 s with a zero-order hold, "
        "its states advanced by exponential Euler, the plant by RK4 at dt = 0.001 s; input "
        f"delay 0 sample(s); no measurement noise): the run diverged at t = "
        f"{float(tr.t_diverged):.6g} s: a state exceeded the state bound 1e+06; tuning needs "
        f"a stable start (revise the gains, dt or tau)")
    assert "Traceback" not in stderr and stdout == ""


def test_an_elasticity_that_is_not_finite_counts_as_breaking(monkeypatch):
    """A loop that depends sensitively on its gains has a tangent that grows without bound
    over the run, until it overflows: its elasticity is None in report.json, "not finite" in
    report.md, and the constraint is fragile in that number, whatever its margin; the warning
    names at most three numbers a constraint, or says "every tuned number". A rough check
    loop's constraint (the delayed input) is left out."""
    el = {(0, "max_abs_u"): {"k[0]": 2.0, "k[1]": 0.5},
          (0, "tv_u"): {"k[0]": float("inf"), "k[1]": -3.0}}
    monkeypatch.setattr(elasticity, "elasticities", lambda problem, z, figures: el)
    checks = [{"name": "max|u|", "key": "max_abs_u", "value": 9.0, "bound": 10.0,
               "relative_margin": 0.1, "met": True},
              {"name": "TV(u)", "key": "tv_u", "value": 50.0, "bound": 100.0,
               "relative_margin": 0.5, "met": True}]
    # a rough check loop's constraint (the delayed input) is left out
    delayed = SimpleNamespace(name="delayed", smooth=False)
    problem = SimpleNamespace(objective=SimpleNamespace(checks=(delayed,)))
    late = {"name": "TV(u), the input delayed 1 sample", "key": "delayed_tv_u", "value": 1.0,
            "bound": 2.0, "relative_margin": 0.5, "met": True}
    sens = elasticity.constraints(problem, None, [*checks, late])
    # 0.9 (1 + 0.01 x 2) = 0.918 <= 1: room; TV(u): half its bound, but k[0] not finite
    assert [r["fragile"] for r in sens["rows"]] == [[], ["k[0]"]]
    assert sens["rows"][1]["elasticity"] == {"k[0]": None, "k[1]": -3.0}
    assert sens["rows"][1]["largest"] == {"number": "k[0]", "elasticity": None}
    assert elasticity.warning(sens) == (
        "a 1 % change of one tuned number breaks a constraint (to first order, nominal "
        "plant): TV(u) (margin 50 % of its bound) by k[0] (elasticity not finite)")
    assert "| `k[0]` | 2 | **not finite** |" in report_md.sensitivity_section(sens)
    many = {"name": "TV(u)", "relative_margin": 0.5, "fragile": ["a", "b", "c", "d", "e"],
            "elasticity": {"a": 9.0, "b": None, "c": -70.0, "d": 60.0, "e": 50.0}}
    assert elasticity.warning({"step": 0.01, "rows": [many]}).endswith(
        "TV(u) (margin 50 % of its bound) by b (elasticity not finite), c (elasticity -70), "
        "d (elasticity 60) and 2 more")
    every = many | {"fragile": ["a", "b"], "elasticity": {"a": None, "b": None}}
    assert elasticity.warning({"step": 0.01, "rows": [every]}).endswith(
        "TV(u) (margin 50 % of its bound) by every tuned number (elasticity not finite)")
