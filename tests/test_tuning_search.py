"""The deployable problem and `dscjax tune`'s methods on the box search (cma, adam): the TV(u)
and max|u| bounds are exact in the report (a hand-made u with known figures), CMA-ES never
evaluates a gradient (counted), each method lowers the objective on a short horizon and
resumes from a pickle-free checkpoint to the very same result, CMA-ES's populations are a
plain CMA-ES's, and a NaN never becomes the best point nor reaches CMA-ES.

One small problem (1 s horizon at dt = 2 ms, k_1 and k_2 tuned), shared by every test: CMA-ES's
batches have one width (population 10), so ONE batched program and one gradient are compiled
for the whole module.
"""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

import dscjax
import tuning
import tuning.runner
from dscjax import metrics
from dscjax import search as box
from dscjax.search import methods
from tuning import report, report_md, search
from tuning.runner import run
from tuning.scales import Scales

STEPS = 4  # iterations of an uninterrupted run; the interrupted one stops at 2
WIDTH = 10  # conftest search_problem's population


def test_constraints_are_exact_on_a_hand_made_trajectory():
    # u on the step grid: 0, 1, -2, 0.5, 0.5, 3 -> TV = 1 + 3 + 2.5 + 0 + 2.5 = 9, max|u| = 3
    u = jnp.array([0.0, 1.0, -2.0, 0.5, 0.5, 3.0])

    @jax.jit
    def figures(u):  # the accumulator the simulation runs on every RK4 step
        acc = metrics.running_init(jnp.float64)
        for k in range(u.size):
            acc = metrics.running_update(acc, jnp.asarray(k), jnp.asarray(0.1 * k), 0.0, u[k],
                                         0.0, 0.1, 0.0, u.size - 1)
        return metrics.finalize(acc, 0.5)

    m = {k: np.asarray(v) for k, v in figures(u).items()} | {
        "diverged": np.asarray(False)}
    assert float(m["tv_u"]) == 9.0 and float(m["max_abs_u"]) == 3.0
    sc = Scales(linf=1.0, l2=1.0, l2_u=1.0, max_u=3.0, u_max=3.5, tv_u=6.0, tv_max=1.5 * 6.0)
    rows = {r["name"]: r for r in report.constraint_checks(sc, m)}
    assert rows["max|u|"] == {"name": "max|u|", "key": "max_abs_u", "value": 3.0, "bound": 3.5,
                              "margin": 0.5, "relative_margin": 0.5 / 3.5, "met": True}
    assert rows["TV(u)"]["value"] == 9.0 and rows["TV(u)"]["margin"] == 0.0
    assert rows["TV(u)"]["met"]  # on the bound: met
    tight = dataclasses.replace(sc, tv_max=8.75)
    tv = {r["name"]: r for r in report.constraint_checks(tight, m)}["TV(u)"]
    assert tv["margin"] == -0.25 and not tv["met"]
    # a diverged plant meets nothing
    assert not any(r["met"] for r in report.constraint_checks(sc, m | {"diverged": True}))


def test_tv_bound_defaults_to_one_and_a_half_start_and_is_one_line_away():
    spec = tuning.ObjectiveSpec()
    assert spec.tv_max == "start" and spec.tv_max_factor == 1.5
    cfg = tuning.config.from_dict({"objective": {"tv_max": "none"}})
    assert cfg.objective.tv_max is None
    with pytest.raises(dscjax.ConfigError, match="tv_max"):
        tuning.config.from_dict({"objective": {"tv_max": -1.0}})


def test_heldout_divergence_is_a_warning_naming_the_count_and_the_robust_option():
    cfg = tuning.TuningConfig()
    stats = {"start": {"n": 256, "n_diverged": 0, "n_refined": 0},
             "tuned": {"n": 256, "n_diverged": 38, "n_refined": 0}}
    w = report_md.heldout_warning({"heldout": stats}, cfg)
    assert "38 of 256 held-out plants" in w and "--batch" in w and "nominal plant only" in w
    robust = dataclasses.replace(cfg, robust=tuning.BatchSpec(batch=8))
    w = report_md.heldout_warning({"heldout": stats}, robust)
    assert "38 of 256" in w and "training batch of 8 plants" in w and "--batch 32" in w
    ok = {"start": stats["start"], "tuned": {"n": 256, "n_diverged": 0, "n_refined": 0}}
    assert report_md.heldout_warning({"heldout": ok}, cfg) is None
    assert report_md.heldout_warning({}, cfg) is None
    # plants that track with a small error but chatter are lost too (issue 38 item 2)
    chatter = {"start": stats["start"] | {"n_chattering": 0},
               "tuned": stats["tuned"] | {"n_chattering": 200}}
    w = report_md.heldout_warning({"heldout": chatter}, cfg)
    assert w.startswith("the tuned gains DIVERGE and CHATTER: diverged on 38 of 256 held-out "
                        "plants (start gains: 0); chatter (chattering index above 1.5) on 200 "
                        "of 256 held-out plants (start gains: 0); they were tuned on ")
    only = {"start": ok["start"] | {"n_chattering": 1},
            "tuned": ok["tuned"] | {"n_chattering": 3}}
    assert report_md.heldout_warning({"heldout": only}, cfg).startswith(
        "the tuned gains CHATTER: chatter (chattering index above 1.5) on 3 of 256 held-out "
        "plants (start gains: 1);")


def test_the_box_follows_the_order_of_the_flat_z():
    # ravel_pytree orders z by name, not in the order the parameters were listed: the box of
    # CMA-ES and of the projected gradient steps must bound tau where tau sits in the flat vector
    from dscjax.selection import Selection

    setup = dscjax.paper_example()
    sel = Selection.build(setup, ("controller.tau", "controller.k", "controller.eps"),
                          bounds={"controller.tau": (0.002, 0.5)})
    z = sel.init(setup)
    lo, hi = sel.z_box(z)
    flat, unravel = ravel_pytree(z)
    assert lo.shape == hi.shape == flat.shape
    lo_t, hi_t = unravel(jnp.asarray(lo)), unravel(jnp.asarray(hi))
    np.testing.assert_allclose(lo_t["controller.tau"], np.log(0.002), rtol=1e-15)
    np.testing.assert_allclose(hi_t["controller.tau"], np.log(0.5), rtol=1e-15)
    for name in ("controller.k", "controller.eps"):
        assert np.all(np.isneginf(lo_t[name])) and np.all(np.isposinf(hi_t[name]))


def _with(problem, **opt):
    cfg = problem.cfg
    new = dataclasses.replace(cfg, optimizer=dataclasses.replace(cfg.optimizer, **opt))
    return dataclasses.replace(problem, cfg=new)


@pytest.fixture(scope="module")
def problems(search_problem):
    # one objective, so every method shares its compiled programs (the batches have one width);
    # conftest's, saved every 2 iterations here
    assert search_problem.cfg.optimizer.steps == STEPS
    p = _with(search_problem, save_interval=2)
    return {"cma": p, "adam": _with(p, name=tuning.Adam())}


@pytest.fixture(scope="module")
def straight(problems, tmp_path_factory):
    """{method: the uninterrupted run of STEPS iterations, with its files}."""
    return {k: run(p, tmp_path_factory.mktemp(k)) for k, p in problems.items()}


def test_problem_bounds_are_the_start_gains(problems):
    p = problems["cma"]
    sc = p.objective.scales
    assert sc.tv_max == pytest.approx(1.5 * sc.tv_u, rel=1e-12)
    assert sc.u_max == pytest.approx(sc.max_u, rel=1e-12)
    assert "tv_bound" in tuning.checkpoint.history_columns(p)


def test_search_programs_simulate_with_the_problems_solver_and_gradient(problems,
                                                                       monkeypatch):
    # simulation.solver and the time-parallel gradient reach the batch and the gradient of
    # the search (spied at the call of dscjax's run while tracing: nothing compiles)
    import dscjax.selection

    class Seen(Exception):
        pass

    seen = []

    def spy(setup, spec, **kwargs):
        seen.append((spec.solver.name, spec.gradient.name))
        raise Seen

    monkeypatch.setattr(dscjax.selection, "run_reported", spy)
    p = problems["cma"]
    sim = p.objective.sim.replace(solver="etdrk4")
    q = dataclasses.replace(p, objective=dataclasses.replace(p.objective, sim=sim))
    flat = jnp.asarray(ravel_pytree(q.z0)[0])[None]
    for program in (search.batch_fn(q), search.grad_fn(q)):
        with pytest.raises(Seen):
            program(flat)
    assert seen == [("etdrk4", "time_parallel")] * 2


def test_evaluations_are_counted_and_only_adam_takes_gradients(problems, straight):
    # the start point, then the population
    assert straight["cma"].trace.evaluations == 1 + STEPS * WIDTH
    assert straight["cma"].trace.gradients == 0
    assert straight["adam"].trace.gradients == straight["adam"].trace.evaluations == STEPS
    # the start point ran padded to the population's batch: one program, one width
    assert problems["cma"].programs["batch"][1].widths == {WIDTH}


@pytest.mark.parametrize("which", ["cma", "adam"])
def test_each_method_lowers_the_objective_and_resumes_to_the_same_result(problems, straight,
                                                                          which, tmp_path):
    p, full = problems[which], straight[which]
    assert full.trace.best_feasible  # the start meets its own bounds, at least
    assert full.trace.best_loss < full.trace.start_loss
    out = tmp_path / "run"
    first = run(_with(p, steps=2), out)
    assert first.trace.iterations == 2
    # the checkpoint is plain arrays and JSON: nothing that would need a pickle to load
    with np.load(out / search.STATE_FILE, allow_pickle=False) as z:
        assert all(z[k].dtype.kind in "fiub" for k in z.files)
    again = run(p, out, resume=True)
    assert again.resumed_from == 2 and again.trace.iterations == STEPS
    _same_run(again, full)
    meta = json.loads((out / "checkpoint.json").read_text())
    assert meta["iteration"] == STEPS and meta["stop_reason"] == f"reached {STEPS} iterations"
    assert meta["gradient_evaluations"] == (STEPS if which == "adam" else 0)
    assert meta["best_loss"] == full.trace.best_loss


def _same_run(a, b):
    np.testing.assert_array_equal(a.trace.best_z, b.trace.best_z)
    assert a.trace.best_loss == b.trace.best_loss
    assert a.trace.evaluations == b.trace.evaluations
    assert [r["best_loss"] for r in a.history] == [r["best_loss"] for r in b.history]
    assert [r["lr"] for r in a.history] == [r["lr"] for r in b.history]


def test_a_nan_is_never_the_best_point_nor_told_to_cma_es(problems):
    """Every batch's first candidate is NaN, the start point's evaluation included: the
    incumbent stays finite and CMA-ES is told a finite fitness."""
    class Nan(search.TuneProblem):
        def evaluate(self, z):
            ev = super().evaluate(z)
            ev.loss[0] = np.nan
            return ev

    sp = Nan(problems["cma"])
    res = box.run(sp, problems["cma"].cfg.optimizer.method(), x0=sp.x0,
                  max_iterations=2)
    assert np.isnan(res.trace.start_loss)
    assert np.isfinite(res.trace.best_loss) and np.all(np.isfinite(res.trace.best_z))
    assert np.all(np.isfinite(res.state.es.arrays()["fitness"]))
    assert (res.state.es.arrays()["fitness"][:, 0] == methods.BAD).all()


def test_cma_es_asks_as_a_plain_cma_es(problems):
    """The tuner's CMA-ES, as docs/tuning.md states it: sigma0 0.3 from z0, seed + 1 (its
    `randn` stream), the box. Its populations are those of a plain
    `cma.CMAEvolutionStrategy` told the same fitness."""
    import cma

    asked = []

    class Seen(search.TuneProblem):
        def evaluate(self, z):
            if len(z) == WIDTH:
                asked.append(np.array(z))
            return super().evaluate(z)

    p = problems["cma"]
    sp = Seen(p)
    spec = p.cfg.optimizer
    res = box.run(sp, spec.method(), x0=sp.x0, max_iterations=4)
    fitness = res.state.es.arrays()["fitness"]
    plain = cma.CMAEvolutionStrategy(
        sp.x0, spec.sigma0, {"seed": spec.seed + 1, "verbose": -9, "popsize": len(fitness[0]),
                             "randn": np.random.RandomState(spec.seed + 1).randn,
                             "bounds": [[x if np.isfinite(x) else None for x in sp.lower],
                                        [x if np.isfinite(x) else None for x in sp.upper]]})
    for g in range(4):
        x = np.asarray(plain.ask(), float)
        np.testing.assert_array_equal(x, asked[g])
        plain.tell(list(x), list(fitness[g]))


def _stop_after(n):
    """A cma `stop` that fires once an instance has been told n generations."""
    def stop(self, *a, **k):
        return {"forced": n} if self.countiter >= n else {}
    return stop


def test_cma_es_restarts_afresh_when_its_own_criteria_stop_it(problems, tmp_path, monkeypatch):
    """CMA-ES's criteria forced to fire after 3 generations of each instance: 8 generations
    are 3 + 3 + 2 (two restarts, each a fresh CMA-ES from the start point); with restarts = 0
    the run ends at 3; runs stopped at 5 and at 6 (the generation of a restart, its
    checkpoint written there) and resumed to 8 equal the uninterrupted one bitwise."""
    import cma

    monkeypatch.setattr(cma.CMAEvolutionStrategy, "stop", _stop_after(3))
    p = _with(problems["cma"], steps=8)
    full = run(p, tmp_path / "full")
    assert full.trace.iterations == 8 and full.trace.restarts == 2
    assert full.stop_reason == "reached 8 iterations"
    assert full.trace.best_loss == min(r["best_loss"] for r in full.history)
    told = box.load(tmp_path / "full" / search.STATE_FILE).arrays
    assert told["fitness"].shape[0] == 2  # the second restart's instance: generations 7, 8
    plain = run(_with(p, restarts=0), tmp_path / "plain")
    assert plain.trace.iterations == 3 and plain.trace.restarts == 0
    assert plain.stop_reason == "CMA-ES stopped: {'forced': 3}"
    for stop_at in (5, 6):
        part = run(_with(p, steps=stop_at), tmp_path / f"part{stop_at}")
        assert part.trace.restarts == (1 if stop_at == 5 else 2)
        again = run(p, tmp_path / f"part{stop_at}", resume=True)
        assert again.trace.restarts == 2 and again.trace.iterations == 8
        _same_run(again, full)
        saved = box.load(tmp_path / f"part{stop_at}" / search.STATE_FILE).arrays
        np.testing.assert_array_equal(saved["told"], told["told"])


def test_a_search_without_a_step_limit_runs_until_its_own_criteria(problems, tmp_path,
                                                                     monkeypatch):
    """steps = None (the default) sets no iteration limit on a CMA-ES method: with CMA-ES's
    criteria forced to fire after 3 generations and 2 restarts allowed, the run ends after
    3 x (1 + 2) = 9 generations, stopped by CMA-ES, not by a count (adam's default, set to 5
    here, does not apply to it)."""
    import cma

    import tuning.config

    monkeypatch.setattr(cma.CMAEvolutionStrategy, "stop", _stop_after(3))
    monkeypatch.setattr(tuning.config, "OPTAX_STEPS", 5)
    p = _with(problems["cma"], steps=None, restarts=2, patience=0)
    assert p.cfg.optimizer.max_steps is None
    res = run(p, tmp_path / "open")
    assert res.trace.iterations == 9 and res.trace.restarts == 2
    assert res.stop_reason.startswith("CMA-ES stopped")
    assert _with(p, name=tuning.Adam()).cfg.optimizer.max_steps == 5


def test_a_run_started_from_z_init_resumes_without_it(problems, tmp_path):
    """The start point is saved (search.npz): a run started from other gains (as adversarial
    rounds start from the last round's) resumes bitwise without the caller passing them
    again."""
    p = problems["cma"]
    z = {k: np.asarray(v) + 0.1 for k, v in p.z0.items()}
    full = run(_with(p, steps=4), tmp_path / "full", z_init=z)
    run(_with(p, steps=2), tmp_path / "part", z_init=z)
    again = run(_with(p, steps=4), tmp_path / "part", resume=True)
    _same_run(again, full)
    np.testing.assert_array_equal(again.trace.start_z, np.asarray(ravel_pytree(z)[0], float))
