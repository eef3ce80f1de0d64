"""The deployable problem and the search tuners (cma, cma_line, cma_path, cma_grad, and the line's
back-off): the TV(u) and max|u| bounds are exact in the report (a hand-made u with known
figures), the ablation switch removes every gradient evaluation (counted), each path lowers the
objective on a short horizon and resumes from a pickle-free checkpoint to the very same result,
the line's wins are counted per step size (forced wins), and a NaN never becomes the best point
nor a direction.

One small problem (1 s horizon at dt = 2 ms, k_1 and k_2 tuned), shared by every test: each
path's batch has the same width (cma: population 7; cma_line, cma_path, cma_grad: 4 + 3 line
points), so ONE batched program and one gradient are compiled for the whole module (and one
of width 4 for the line back-off's generations without the line).
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
from dscjax.cmaes import ReplayCMA
from dscjax.config import SimOptions
from tuning import report, search
from tuning.objective import Scales
from tuning.runner import run

STEPS = 4  # generations of an uninterrupted run; the interrupted one stops at 2


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
    assert rows["max|u|"] == {"name": "max|u|", "value": 3.0, "bound": 3.5, "margin": 0.5,
                              "relative_margin": 0.5 / 3.5, "met": True}
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
    stats = {"start": {"n": 256, "n_diverged": 0}, "tuned": {"n": 256, "n_diverged": 38}}
    w = report.heldout_warning({"heldout": stats}, cfg)
    assert "38 of 256 held-out plants" in w and "--batch" in w and "nominal plant only" in w
    robust = dataclasses.replace(cfg, robust=tuning.BatchSpec(batch=8))
    w = report.heldout_warning({"heldout": stats}, robust)
    assert "38 of 256" in w and "training batch of 8 plants" in w and "--batch 32" in w
    ok = {"start": stats["start"], "tuned": {"n": 256, "n_diverged": 0}}
    assert report.heldout_warning({"heldout": ok}, cfg) is None
    assert report.heldout_warning({}, cfg) is None


def test_replayed_cma_es_continues_exactly_without_pickles():
    # ask/tell/inject on a quadratic; a fresh strategy replaying the stored arrays (plain
    # floats, as in search.npz) asks for the very same next population
    def make():
        return ReplayCMA(np.ones(3), 0.5, {"seed": 3, "verbose": -9, "popsize": 5,
                                           "randn": np.random.RandomState(3).randn})

    a = make()
    for g in range(4):
        x = a.ask()
        a.tell(x, (x ** 2).sum(axis=1))
        if g % 2:
            a.inject(0.5 * x[0])
    saved = {k: np.array(v) for k, v in a.arrays().items()}
    assert saved["fitness"].shape == (4, 5) and np.isnan(saved["injected"][0]).all()
    b = make()
    b.replay(saved)
    np.testing.assert_array_equal(b.ask(), a.ask())
    c = make()
    with pytest.raises(ValueError, match="replay"):
        c.replay(saved | {"asked": saved["asked"] + 1.0})


def test_the_box_follows_the_order_of_the_flat_z():
    # ravel_pytree orders z by name, not in the order the parameters were listed: the box of
    # CMA-ES and of the line search must bound tau where tau sits in the flat vector
    from tuning.params import Selection

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


def _problem():
    # forward mode: 2 tangents, the cheapest gradient to compile for two numbers
    spec = tuning.OptimizerSpec(name="cma_grad", steps=STEPS, save_interval=2, popsize=4,
                                line_points=3, background_compile=False, time_limit=None,
                                gradient="forward")
    cfg = tuning.TuningConfig(params=("controller.k",), optimizer=spec,
                              objective=tuning.ObjectiveSpec(window_start=0.5),
                              heldout=tuning.BatchSpec(batch=0))
    return tuning.build_problem(dscjax.paper_example(), SimOptions(t_final=1.0, dt=2e-3), cfg)


def _with(problem, **opt):
    cfg = problem.cfg
    new = dataclasses.replace(cfg, optimizer=dataclasses.replace(cfg.optimizer, **opt))
    return dataclasses.replace(problem, cfg=new)


@pytest.fixture(scope="module")
def problems():
    # one objective, so every path shares its compiled programs (the batches have one width)
    p = _problem()
    return {"cma_grad": p, "cma_line": _with(p, name="cma_line"),
            "cma_path": _with(p, name="cma_path"), "ablation": _with(p, grad_every=0),
            "cma": _with(p, name="cma", popsize=7),
            # far steps, which lose here: the back-off is under way where a run stops at 2
            "backoff": _with(p, name="cma_path", line_backoff=2, line_min=3.0, line_max=5.0),
            # the line in generations 0-1 only: an interrupted run stops at the switch, and
            # the resumed one compiles the population's program and runs without the line
            "early": _with(p, name="cma_path", line_generations=2)}


@pytest.fixture(scope="module")
def straight(problems, tmp_path_factory):
    """{path: the uninterrupted run of STEPS generations, with its files}."""
    return {k: run(p, tmp_path_factory.mktemp(k)) for k, p in problems.items()}


def test_problem_bounds_are_the_start_gains(problems):
    p = problems["cma_grad"]
    sc = p.objective.scales
    assert sc.tv_max == pytest.approx(1.5 * sc.tv_u, rel=1e-12)
    assert sc.u_max == pytest.approx(sc.max_u, rel=1e-12)
    assert "tv_bound" in tuning.runner.history_columns(p)


def test_search_programs_simulate_with_the_problems_solver_and_gradient(problems,
                                                                       monkeypatch):
    # simulation.solver and the time-parallel gradient reach the batch and the gradient of
    # the search methods (spied at the call of dscjax's run while tracing: nothing compiles)
    import tuning.objective

    class Seen(Exception):
        pass

    seen = []

    def spy(*args, **kwargs):
        seen.append((kwargs["solver"], kwargs["gradient"]))
        raise Seen

    monkeypatch.setattr(tuning.objective, "run", spy)
    p = problems["cma_grad"]
    sim = dataclasses.replace(p.objective.sim, solver="etdrk4")
    q = dataclasses.replace(p, objective=dataclasses.replace(p.objective, sim=sim))
    flat = jnp.asarray(ravel_pytree(q.z0)[0])
    for program, x in ((search.batch_fn(q), flat[None]), (search.grad_fn(q), flat)):
        with pytest.raises(Seen):
            program.lower(x)
    assert seen == [("etdrk4", "time_parallel")] * 2


def test_combining_problems_of_a_search_method_is_refused_naming_the_field(problems):
    with pytest.raises(dscjax.ConfigError, match="tuning.optimizer.name"):
        tuning.combine([problems["cma_line"], problems["cma_line"]])


def test_ablation_switch_removes_every_gradient_evaluation(problems, straight, monkeypatch):
    calls = []
    real = search.value_and_grad

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(search, "value_and_grad", counting)
    for off in ("ablation", "cma_line", "cma_path", "cma", "backoff", "early"):
        s = search.Search.open(problems[off], None, False, 0.0)
        assert s.grad is None  # nothing to trace or compile
        assert straight[off].gradient_evaluations == 0
    assert calls == []  # never traced, never run
    # the start, then population + line points (+ the gradient's own evaluation)
    assert straight["ablation"].evaluations == 1 + STEPS * (4 + 3)
    assert straight["cma_path"].evaluations == 1 + STEPS * (4 + 3)
    assert straight["cma"].evaluations == 1 + STEPS * 7
    # line_generations = 2: the line in the first 2 generations, the population alone after
    assert straight["early"].evaluations == 1 + 2 * (4 + 3) + (STEPS - 2) * 4
    on = straight["cma_grad"]
    assert on.gradient_evaluations == STEPS  # one per generation
    assert on.evaluations == 1 + STEPS * (4 + 3 + 1)


@pytest.mark.parametrize("which", ["cma_grad", "cma_line", "cma_path", "cma", "backoff",
                                   "early"])
def test_each_path_lowers_the_objective_and_resumes_to_the_same_result(problems, straight,
                                                                        which, tmp_path):
    p, full = problems[which], straight[which]
    assert full.state.best_feasible  # the start meets its own bounds, at least
    assert full.state.best_loss < full.state.start_loss
    out = tmp_path / "run"
    first = run(_with(p, steps=2), out)
    assert first.state.iteration == 2
    # the checkpoint is plain arrays and JSON: nothing that would need a pickle to load
    with np.load(out / search.STATE_FILE, allow_pickle=False) as z:
        assert all(z[k].dtype.kind in "fiu" for k in z.files)
    again = run(p, out, resume=True)
    assert again.resumed_from == 2 and again.state.iteration == STEPS
    np.testing.assert_array_equal(again.state.best_flat, full.state.best_flat)
    assert again.state.best_loss == full.state.best_loss
    assert again.state.evaluations == full.state.evaluations
    assert again.state.line_wins == full.state.line_wins
    # the line's wins per step size: one count per line point
    assert full.state.line_step_wins.shape == ((0,) if which == "cma" else (3,))
    np.testing.assert_array_equal(again.state.line_step_wins, full.state.line_step_wins)
    assert (again.state.line_losses, again.state.line_skip) == (full.state.line_losses,
                                                                full.state.line_skip)
    if which == "backoff":  # the back-off was under way where the first run stopped,
        assert first.state.line_losses > 0  # and it skipped lines (4 candidates, not 7)
        assert full.state.evaluations < 1 + STEPS * (4 + 3)
    meta = json.loads((out / "checkpoint.json").read_text())
    assert meta["iteration"] == STEPS
    assert meta["gradient_evaluations"] == (STEPS if which == "cma_grad" else 0)


def test_a_nan_is_never_the_best_point_nor_a_direction(problems, straight):
    assert not search.better(True, float("nan"), False, 1.0)
    assert not search.better(False, float("inf"), False, float("inf"))
    s = search.Search.open(_with(problems["cma_grad"], steps=2), None, False, 0.0)
    s.compile()  # from the objective's cache: `straight` compiled it
    # every gradient is NaN: the line search falls back to random directions, the run goes on
    real = s.grad
    s.grad = lambda x: (lambda r: (r[0], r[1], jnp.full_like(r[2], jnp.nan)))(real(x))
    # and one candidate of each batch, the start point's included, is NaN
    real_batch = s.batch

    def nan_batch(x):
        r = real_batch(x)
        return r | {"loss": r["loss"].at[0].set(jnp.nan)}

    s.batch = nan_batch
    for _ in range(2):
        s.generation()
    assert np.isfinite(s.state.best_loss) and np.all(np.isfinite(s.state.best_flat))
    assert s.state.gradient_evaluations == 2
    assert np.all(np.isfinite(s.state.cma.arrays()["fitness"]))  # CMA-ES was told no NaN


def test_the_path_direction_has_unit_mahalanobis_length_and_never_a_nan():
    # cma_path's line follows CMA-ES's evolution path p_c, scaled to d' C^-1 d = 1 (checked
    # against an explicit inverse); a zero or non-finite path gives no direction (random then)
    rng = np.random.default_rng(3)
    a = rng.standard_normal((4, 4))
    cov = a @ a.T + np.eye(4)
    es = type("Es", (), {})()
    es.pc = rng.standard_normal(4)
    d = search._path_direction(es, cov)
    assert d @ np.linalg.inv(cov) @ d == pytest.approx(1.0, rel=1e-12)
    c = d / es.pc
    np.testing.assert_allclose(c, c[0], rtol=1e-12)
    assert c[0] > 0
    for bad in (np.zeros(4), np.array([1.0, np.nan, 0.0, 0.0]), np.full(4, np.inf)):
        es.pc = bad
        assert search._path_direction(es, cov) is None


def test_cma_path_draws_its_line_along_the_evolution_path(problems, monkeypatch):
    """cma_path asks for the path's direction in every generation and takes it once p_c is
    non-zero (CMA-ES leaves p_c at zero while its hsig test fails, early on); cma_line never
    asks for it."""
    used = {"calls": 0, "directions": 0}
    real = search._path_direction

    def counting(es, cov):
        d = real(es, cov)
        used["calls"] += 1
        used["directions"] += d is not None
        return d

    monkeypatch.setattr(search, "_path_direction", counting)
    run(problems["cma_line"], None)
    assert used == {"calls": 0, "directions": 0}
    run(problems["cma_path"], None)
    assert used["calls"] == STEPS and used["directions"] >= 1


@pytest.mark.parametrize("line_wins, generations, taken, counters", [
    # a line that always loses is skipped 1, 2, then min(4, line_backoff = 2) generations;
    # after the 4th loss (generation 8): 4 losses, 2 generations to skip
    (False, 0, [0, 2, 5, 8], (4, 2)),
    (True, 0, list(range(9)), (0, 0)),  # one that always wins is never skipped
    # line_generations = 6 ends both: no line from generation 6 on, and no more losses
    # counted (3, at generation 5), the countdown at 0
    (False, 6, [0, 2, 5], (3, 0)),
    (True, 6, list(range(6)), (0, 0)),
])
def test_line_backoff_skips_a_losing_line_for_doubling_generations(problems, line_wins,
                                                                    generations, taken,
                                                                    counters):
    """line_backoff = 2: which generations simulate the line (population 4 + 3 line points)
    and which CMA-ES's population alone (4), when every line point loses or wins; counted
    on the batches simulated, with the losses forced on the real programs' output."""
    p = _with(problems["backoff"], steps=9, line_generations=generations)
    s = search.Search.open(p, None, False, 0.0)
    s.compile()  # from the objective's cache: `straight` compiled both widths
    widths = []

    def forced(program):
        def run_(x):
            widths.append(x.shape[0])
            r = program(x)
            if x.shape[0] == 7:  # the line rows: a new best each time, or never one
                step = -1.0 - len(widths) if line_wins else 1e9
                r = r | {"loss": r["loss"].at[4:].set(step),
                         "feasible": r["feasible"].at[4:].set(line_wins)}
            return r
        return run_

    s.batch, s.pop_batch = forced(s.batch), forced(s.pop_batch)
    for _ in range(9):
        s.generation()
    assert widths[0] == 4  # the start point, padded to the narrower batch
    assert [g for g, w in enumerate(widths[1:]) if w == 7] == taken
    assert set(widths[1:]) <= {4, 7}
    assert s.state.line_wins == (len(taken) if line_wins else 0)
    assert s.state.evaluations == 1 + 9 * 4 + 3 * len(taken)
    assert (s.state.line_losses, s.state.line_skip) == counters


@pytest.mark.parametrize("winners, counts", [
    # the line point that wins each of 6 generations (None: none does), and the counts by
    # step size, shortest first
    ([2, 0, 2, None, 1, 2], [1, 1, 3]),
    ([None, None, 1, 1, 1, None], [0, 3, 0]),
])
def test_line_wins_are_counted_per_step_size_and_resume(problems, winners, counts,
                                                        tmp_path):
    """cma_path with 3 line points (population 4): the loss and feasibility of the line rows
    are forced on the real program's output so that one chosen step size wins, or none."""
    p = _with(problems["cma_path"], steps=len(winners), save_interval=1)
    s = search.Search.open(p, tmp_path, False, 0.0)
    s.compile()  # from the objective's cache: `straight` compiled it
    calls = []
    real = s.batch

    def forced(x):
        r = real(x)
        g = len(calls) - 1  # the generation (-1: the start point's evaluation)
        calls.append(g)
        if g < 0:
            return r
        loss = r["loss"].at[4:].set(1e9)  # infeasible, far worse: the line loses
        feas = r["feasible"].at[4:].set(False)
        if winners[g] is not None:  # a new best, feasible, at that step size
            loss = loss.at[4 + winners[g]].set(-1.0 - g)
            feas = feas.at[4 + winners[g]].set(True)
        return r | {"loss": loss, "feasible": feas}

    s.batch = forced
    for _ in winners:
        s.generation()
    assert len(calls) == 1 + len(winners)
    assert s.state.line_step_wins.dtype == np.int64
    assert s.state.line_step_wins.tolist() == counts
    assert s.state.line_wins == sum(w is not None for w in winners)
    s.save()
    again = search.Search.open(p, tmp_path, True, 0.0)
    assert again.state.iteration == len(winners)
    assert again.state.line_step_wins.tolist() == counts
    # a file from before the count (no line_step_wins in it) resumes with zeros
    arrays = np.load(tmp_path / search.STATE_FILE)
    old = {k: arrays[k] for k in arrays.files if k != "line_step_wins"}
    dscjax.files.write_npz(tmp_path / search.STATE_FILE, old)
    before = search.Search.open(p, tmp_path, True, 0.0)
    assert before.state.line_step_wins.tolist() == [0, 0, 0]
    assert before.state.line_wins == sum(w is not None for w in winners)


def test_line_backoff_is_a_whole_number_checked_in_one_line(problems):
    cfg = tuning.config.from_dict({"optimizer": {"line_backoff": 8}})
    assert cfg.optimizer.line_backoff == 8
    with pytest.raises(dscjax.ConfigError,
                       match=r"^tuning.optimizer.line_backoff must be .*>= 0.*-1"):
        tuning.config.from_dict({"optimizer": {"line_backoff": -1}})
    # in the resume fingerprint only when on, so that runs from before it still resume
    problem = problems["cma_path"]
    assert "line_backoff" not in problem.describe()["optimizer"]
    assert _with(problem, line_backoff=8).describe()["optimizer"]["line_backoff"] == 8
    # and the report's method sentence says so (only when it is on)
    on = report.method_sentence(cfg.optimizer, "forward")
    assert "skipped for min(2^(k-1), 8) generations" in on
    assert "skipped" not in report.method_sentence(tuning.OptimizerSpec(), "forward")


def test_line_generations_is_a_whole_number_checked_in_one_line():
    cfg = tuning.config.from_dict({"optimizer": {"line_generations": 20}})
    assert cfg.optimizer.line_generations == 20
    for bad in (-2, 2.5):
        with pytest.raises(dscjax.ConfigError,
                           match=rf"^tuning.optimizer.line_generations must be an integer.*"
                           rf"\(got {bad}\)$"):
            tuning.config.from_dict({"optimizer": {"line_generations": bad}})
    # the report's method sentence says when the line stops (not at 0: every generation)
    assert "first 20 generations only" in report.method_sentence(cfg.optimizer, "forward")
    off = tuning.OptimizerSpec(line_generations=0)
    assert "generations only" not in report.method_sentence(off, "forward")


@pytest.mark.parametrize("inject", [True, False])
def test_line_inject_off_leaves_cma_es_as_told(problems, inject, tmp_path):
    """cma_path with its line forced to win every generation: injected (the default) the
    winners enter CMA-ES's populations; with line_inject = false the populations are those
    of a plain `cma.CMAEvolutionStrategy` (same x0, sigma0, options) told the same fitness."""
    import cma

    p = _with(problems["cma_path"], line_inject=inject)
    s = search.Search.open(p, tmp_path, False, 0.0)
    s.compile()
    real = s.batch

    def line_wins(x):
        r = real(x)
        if np.all(x == x[:1]):  # the start point's evaluation (one point, tiled)
            return r
        return r | {"loss": r["loss"].at[4].set(-1.0 - len(asked)),
                    "feasible": r["feasible"].at[4].set(True)}

    s.batch = line_wins
    asked = []
    for _ in range(4):
        s.generation()
        asked.append(s.state.cma.asked.copy())
    assert s.state.line_wins == 4
    fitness = s.state.cma.arrays()["fitness"]
    es = s.state.cma.es
    # the tuner's CMA-ES, as docs/tuning.md states it: sigma0 0.3 from z0, seed + 1, the box
    spec = p.cfg.optimizer
    lo, hi = search.z_box(p)
    plain = cma.CMAEvolutionStrategy(
        np.asarray(ravel_pytree(p.z0)[0], float), spec.sigma0,
        {"seed": spec.seed + 1, "verbose": -9, "popsize": es.popsize,
         "randn": np.random.RandomState(spec.seed + 1).randn,
         "bounds": [[x if np.isfinite(x) else None for x in lo],
                    [x if np.isfinite(x) else None for x in hi]]})
    same = []
    for g in range(4):
        x = np.asarray(plain.ask(), float)
        same.append(np.array_equal(x, asked[g]))
        plain.tell(list(x), list(fitness[g]))
    assert es.popsize == 4
    # generation 0 is asked before any injection; from generation 1 on they differ only if
    # winners were injected
    assert same == [True, True, True, True] if not inject else same == [True, False, False,
                                                                        False]


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
    p = _with(problems["cma_path"], steps=8, save_interval=1)
    full = run(p, tmp_path / "full")
    assert full.state.iteration == 8 and full.state.restarts == 2
    assert full.state.es.countiter == 2  # the second restart's instance: generations 7, 8
    assert full.stop_reason == "reached 8 generations"
    # each restart is a fresh CMA-ES from the start point (the start gains' z), sigma0 and a
    # seed of its own; the incumbent is the best over all three instances
    start = np.asarray(ravel_pytree(p.z0)[0], float)
    np.testing.assert_array_equal(np.asarray(full.state.es.x0, float), start)
    assert full.state.es.sigma0 == p.cfg.optimizer.sigma0
    # restart r's seed: SeedSequence([seed, r]), not seed + 1 + r (another run's stream)
    assert full.state.es.opts["seed"] == int(
        np.random.SeedSequence([p.cfg.optimizer.seed, 2]).generate_state(1)[0])
    assert full.state.best_loss == min(r["best_loss"] for r in full.history)
    plain = run(_with(p, restarts=0), tmp_path / "plain")
    assert plain.state.iteration == 3 and plain.state.restarts == 0
    assert plain.stop_reason.startswith("CMA-ES stopped")
    for stop_at in (5, 6):
        part = run(_with(p, steps=stop_at), tmp_path / f"part{stop_at}")
        assert part.state.restarts == (1 if stop_at == 5 else 2)
        again = run(p, tmp_path / f"part{stop_at}", resume=True)
        assert again.state.restarts == 2 and again.state.iteration == 8
        np.testing.assert_array_equal(again.state.best_flat, full.state.best_flat)
        np.testing.assert_array_equal(np.asarray(again.state.es.x0, float), start)
        np.testing.assert_array_equal(again.state.cma.asked, full.state.cma.asked)


def test_a_search_without_a_step_limit_runs_until_its_own_criteria(problems, tmp_path,
                                                                     monkeypatch):
    """steps = None (the default) sets no generation limit on a search: with CMA-ES's
    criteria forced to fire after 3 generations and 2 restarts allowed, the run ends after
    3 x (1 + 2) = 9 generations, stopped by CMA-ES, not by a count (the optax rules' default,
    set to 5 here, does not apply to it)."""
    import cma

    import tuning.optimize

    monkeypatch.setattr(cma.CMAEvolutionStrategy, "stop", _stop_after(3))
    monkeypatch.setattr(tuning.optimize, "OPTAX_STEPS", 5)
    p = _with(problems["cma_path"], steps=None, restarts=2, patience=0)
    assert p.cfg.optimizer.max_steps is None
    res = run(p, tmp_path / "open")
    assert res.state.iteration == 9 and res.state.restarts == 2
    assert res.stop_reason.startswith("CMA-ES stopped")


def test_a_run_started_from_z_init_resumes_without_it(problems, tmp_path):
    """The start point is saved (search.npz `start_flat`): a run started from other gains
    (as adversarial rounds start from the last round's) resumes bitwise without the caller
    passing them again; before, CMA-ES was rebuilt from the problem's z0 and the replay was
    refused."""
    p = problems["cma_path"]
    z = {k: np.asarray(v) + 0.1 for k, v in p.z0.items()}
    full = run(_with(p, steps=4), tmp_path / "full", z_init=z)
    run(_with(p, steps=2, save_interval=1), tmp_path / "part", z_init=z)
    again = run(_with(p, steps=4), tmp_path / "part", resume=True)
    np.testing.assert_array_equal(again.state.best_flat, full.state.best_flat)
    np.testing.assert_array_equal(again.state.cma.asked, full.state.cma.asked)
    np.testing.assert_array_equal(again.state.start_flat,
                                  np.asarray(ravel_pytree(z)[0], float))
