"""Stiff loops: the exponential (ETDRK4) step on a stiff problem with a known solution, and
per-trajectory refinement (a divergence of RK4 that a stiffness-aware or smaller step removes is
not reported)."""

from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
import pytest
from compilations import counted

import dscjax
from dscjax.divergence import level_spec
from dscjax.hysteresis import closed_form
from dscjax.integrate import ETDRK4, STATUS_OK, integrate

ALPHA, LAM, PSI = 2.0e4, 1.432, 0.105


def _hysteresis_driven_by_sine(t, w, args):
    """Eq. (4) driven open-loop by v = sin t (rising on [0, pi/2])."""
    dv = jnp.cos(t)
    return ALPHA * jnp.abs(dv) * (LAM * jnp.sin(t) - w) + PSI * dv, dv


def _rate(t, w, args, dv):
    return ALPHA * jnp.abs(dv)


def test_exponential_step_solves_a_stiff_hysteresis_where_rk4_blows_up():
    # alpha |v'| dt = 20 at t = 0: ten times RK4's stability limit (2.785)
    dt, n = 1e-3, 1500
    rk4 = integrate(_hysteresis_driven_by_sine, jnp.array(0.0), dt, n, ())
    assert int(rk4.status.code) != STATUS_OK
    res = integrate(_hysteresis_driven_by_sine, jnp.array(0.0), dt, n, (), rates=_rate,
                    solver=ETDRK4())
    assert int(res.status.code) == STATUS_OK
    t = np.arange(n + 1) * dt
    exact = np.asarray(closed_form(np.sin(t), 0.0, 0.0, ALPHA, LAM, PSI, 1))
    # exact for the frozen linear decay; the rate's change within a step costs ~1e-8 here
    err = np.max(np.abs(np.asarray(res.ys) - exact))
    assert err < 1e-6, err


def test_refinement_leaves_healthy_members_bitwise_and_matches_a_finer_run(paper_setup):
    ov = {"hysteresis.alpha": jnp.array([0.7, 10.0, 1.3]),
          "hysteresis.lam": jnp.array([1.2, 0.15, 1.7])}
    plain = dscjax.simulate_batch(paper_setup, ov, 2.0, 1e-3, save_every=100, refine=0)
    refined = dscjax.simulate_batch(paper_setup, ov, 2.0, 1e-3, save_every=100)
    assert np.asarray(plain.diverged).tolist() == [False, True, False]
    assert np.asarray(refined.diverged).tolist() == [False, False, False]
    j = int(refined.refinements[1])
    assert np.asarray(refined.refinements).tolist() == [0, j, 0] and j >= 1
    for a, b in zip(jax_leaves(plain), jax_leaves(refined), strict=True):
        np.testing.assert_array_equal(np.asarray(a)[[0, 2]], np.asarray(b)[[0, 2]])
    # the refined member is exactly the exponential step's run at its level, same save times
    solver, m = dscjax.refinement_level(j)
    assert isinstance(solver, dscjax.ETDRK4)
    one = dscjax.simulate(dscjax.params.set_many(paper_setup, {
        "hysteresis.alpha": 10.0, "hysteresis.lam": 0.15}), 2.0, 1e-3 / 2**m,
        save_every=100 * 2**m, refine=0, solver=solver)
    np.testing.assert_array_equal(np.asarray(refined.t[1]), np.asarray(one.t))
    np.testing.assert_allclose(np.asarray(refined.x[1]), np.asarray(one.x), rtol=0, atol=1e-12)
    assert float(refined.dt[1]) == 1e-3 / 2**m
    # and tracks like a fine classical RK4 run (dt = 1e-4) of the same plant
    fine = dscjax.simulate(dscjax.params.set_many(paper_setup, {
        "hysteresis.alpha": 10.0, "hysteresis.lam": 0.15}), 2.0, 1e-4, save_every=1000)
    assert int(fine.refinements) == 0
    np.testing.assert_allclose(np.asarray(refined.x[1, :, 0]), np.asarray(fine.x[:, 0]), atol=2e-5)
    assert abs(float(refined.metrics["linf_error_window"][1])
               - float(fine.metrics["linf_error_window"])) < 3e-4


def test_a_trajectory_that_diverges_at_every_step_reports_the_smallest(paper_setup):
    # x1' = x2 + 50 x1^2 from x1(0) = 3 blows up within ~7 ms, whatever the step
    with counted() as traced:
        batch = dscjax.simulate_batch(paper_setup, {
            "plant.theta": jnp.array([[0.1, 0.0], [50.0, 0.0]]),
            "plant.x0": jnp.array([[0.08, 0.1], [3.0, 0.1]])}, 2.0, 2e-3, refine=2)
    # the run asked for and one program for both levels (their step count is traced)
    assert traced["run_reported"] == 2
    assert np.asarray(batch.diverged).tolist() == [False, True]
    assert np.asarray(batch.refinements).tolist() == [0, 2]
    assert float(batch.dt[1]) == pytest.approx(1e-3)  # level 2: ETDRK4 at dt / 2
    assert np.isnan(float(batch.metrics["linf_error"][1]))
    # the levels (not the run asked for) step no more once all they re-run has diverged
    spec = dscjax.RunSpec.make(2.0, 2e-3)
    assert [level_spec(spec, j).skip_diverged for j in range(3)] == [False, True, True]
    # a level's spec rebuilt from its table is the same run: its steps, saved times and levels
    spec = dscjax.RunSpec.make(2.0, 2e-3, save_every=10)
    for j in (1, 2):
        again, m = level_spec(spec, j).replace(refine=0), 2 ** (j - 1)
        assert again.skip_diverged and again.dt == spec.dt / m and again.t_final == spec.t_final
        assert (again.n_steps, again.save_every) == (spec.n_steps * m, spec.save_every * m)


def test_single_run_is_refined_and_says_so(paper_setup):
    traj = dscjax.simulate(paper_setup, 2.0, 2e-2, save_every=5)
    assert not bool(traj.diverged) and int(traj.refinements) >= 1
    solver, m = dscjax.refinement_level(int(traj.refinements))
    assert float(traj.dt) == 2e-2 / 2**m
    np.testing.assert_allclose(np.asarray(traj.t), np.arange(21) * 0.1, atol=1e-12)


def jax_leaves(traj):
    import jax

    return [x for x in jax.tree.leaves(traj) if np.ndim(x) > 0]


def test_tuning_report_refines_a_plant_that_diverges_only_numerically(paper_setup):
    """The tuner's held-out (and training) figures: a plant whose classical RK4 run diverges
    at the tuning's step but tracks once refined is counted as refined, not diverged, with
    the figures of the refined run; the other plants are left as they were."""
    import tuning
    from dscjax.runspec import RunSpec
    from tuning import report, report_md

    # the continuous loop alone (the sampled constraint off: its refinement is the same code)
    problem = tuning.build_problem(paper_setup, RunSpec.make(t_final=2.0),
                                   tuning.TuningConfig())
    ov = {"hysteresis.alpha": np.array([0.7, 10.0, 1.3]),
          "hysteresis.lam": np.array([1.2, 0.15, 1.7])}
    z = problem.z0
    before = report._host(problem.objective.per_plant(z, {k: jnp.asarray(v)
                                                          for k, v in ov.items()}))
    assert np.asarray(before["diverged"]).astype(bool).tolist() == [False, True, False]
    after = report.refined(problem, z, ov, before)
    assert np.asarray(after["diverged"]).astype(bool).tolist() == [False, False, False]
    j = int(after["refined"][1])
    assert after["refined"].tolist() == [0, j, 0] and j >= 1
    for key in [k for k in report_md.STATS_METRICS + ("loss",) if k in before]:  # (no sampled_*)
        assert key in after, key
        np.testing.assert_array_equal(after[key][[0, 2]], np.asarray(before[key])[[0, 2]])
    np.testing.assert_array_equal(after["loss"], before["loss"])  # the objective's, at dt
    solver, m = dscjax.refinement_level(j)
    one = dscjax.simulate(dscjax.params.set_many(paper_setup, {
        "hysteresis.alpha": 10.0, "hysteresis.lam": 0.15}), 2.0, 1e-3 / 2**m, refine=0,
        solver=solver)
    for key in ("linf_error_window", "l2_error_window", "max_abs_u", "l2_u", "tv_u"):
        # a sum over 2**m * 2000 steps, batched or not: round-off of the summation order
        assert after[key][1] == pytest.approx(float(one.metrics[key]), rel=1e-9), key
    # a check loop's figures are refined alike, each exact constraint's among them (here a
    # check loop that is the loop tuned again: the same programs, nothing compiled anew)
    keys = {"diverged": "diverged", "linf_window": "linf_error_window",
            "max_abs_u": "max_abs_u", "tv_u": "tv_u"}
    again = SimpleNamespace(name="again", sim=problem.objective.sim)
    twice = SimpleNamespace(setup_at=problem.setup_at, objective=SimpleNamespace(
        sim=problem.objective.sim, checks=(again,)))
    # (the loop tuned already refined: `after`'s rows; only the check loop's are re-run)
    checked = report.refined(twice, z, ov, after | {f"again_{k}": before[v]
                                                    for k, v in keys.items()})
    assert checked["again_refined"].tolist() == [0, j, 0]
    for k, v in keys.items():
        np.testing.assert_array_equal(checked[f"again_{k}"], after[v])
    stats = report.batch_stats(after)
    assert (stats["n_tracked"], stats["n_refined"], stats["n_diverged"]) == (2, 1, 0)
    # reported as sweeps report their rows
    summary = {"heldout": {"start": report.batch_stats(before | {"refined": np.zeros(3)}),
                           "tuned": stats}}
    assert report_md.batch_counts(summary) == (
        "held-out batch (3 plants, start -> tuned gains): tracked 2 -> 2; tracked after "
        "refinement 0 -> 1; diverged at every step tried 1 -> 0; of the plants that did not "
        "diverge, chattering (chattering index above 1.5) 0 -> 0")
    # a plant the tuned gains track only once refined is named in the warning (the loop is
    # stiff at the tuning's step: a digital controller at that rate could not run the gains),
    # not counted as diverged
    warning = report_md.heldout_warning(summary, problem.cfg)
    assert ("RK4 diverged at dt (the loop stiff there; tracked only once refined) on 1 of 3 "
            "held-out plants (start gains: 0)") in warning and "diverged on" not in warning


def test_an_unstable_sampled_loop_is_refined_once_and_named_in_one_line(paper_setup):
    """A sampled loop that diverges because of its sample time and delay diverges again at
    the same time once refined: one refinement, then one line naming Ts and the delay (not
    six refinements and "reduce dt")."""
    from dscjax.runspec import RunSpec
    from dscjax.simulate import counted_levels

    spec = RunSpec.make(2.0, 1e-3, sample_time=0.04, delay=2)
    assert spec.refine > 1 and counted_levels(spec) == 1
    assert counted_levels(RunSpec.make(2.0, 1e-3)) == spec.refine  # continuous: all of them
    plain = dscjax.simulate(paper_setup, spec=spec.replace(refine=0), throw=False)
    assert bool(plain.diverged)
    with pytest.raises(dscjax.DivergenceError) as err:
        dscjax.simulate(paper_setup, spec=spec)
    traj = err.value.trajectory
    assert int(traj.refinements) == 1
    # the refined run (ETDRK4 at dt) fails within one sample period of the plain one
    assert abs(float(traj.t_diverged) - float(plain.t_diverged)) <= 0.04
    text = str(err.value)
    assert "\n" not in text and "Reduce dt" not in text
    assert text.startswith("the sampled loop is unstable (sample time 0.04 s, input delay 2 "
                           "samples): it diverges at t = ")
