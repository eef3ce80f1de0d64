"""The deployable problem and the cma_grad tuner: the TV(u) and max|u| bounds are exact in
the report (a hand-made u with known figures), the ablation switch removes every gradient
evaluation (counted), each path lowers the objective on a short horizon and resumes from a
checkpoint to the very same result, and a NaN never becomes the best point nor a direction.

One small problem (1.5 s horizon, k_1 and k_2 tuned), shared, so each program compiles once.
"""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dscjax
import tuning
import tuning.runner
from dscjax import metrics
from dscjax.config import SimOptions
from tuning import report, search
from tuning.objective import Scales
from tuning.runner import run


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


def _problem(**opt):
    # forward mode: 2 tangents, the cheapest gradient to compile for two numbers
    spec = tuning.OptimizerSpec(name="cma_grad", steps=4, save_interval=2, popsize=4,
                                line_points=3, background_compile=False, time_limit=None,
                                gradient="forward", **opt)
    cfg = tuning.TuningConfig(params=("controller.k",), optimizer=spec,
                              objective=tuning.ObjectiveSpec(window_start=0.5),
                              heldout=tuning.BatchSpec(batch=0))
    return tuning.build_problem(dscjax.paper_example(), SimOptions(t_final=1.5), cfg)


@pytest.fixture(scope="module")
def problems():
    # one objective, so both paths share its compiled programs (the batch has the same width)
    p = _problem()
    return {"gradient": p, "ablation": _with(p, grad_every=0)}


def _with(problem, **opt):
    cfg = problem.cfg
    new = dataclasses.replace(cfg, optimizer=dataclasses.replace(cfg.optimizer, **opt))
    return dataclasses.replace(problem, cfg=new)


def test_problem_bounds_are_the_start_gains(problems):
    p = problems["gradient"]
    sc = p.objective.scales
    assert sc.tv_max == pytest.approx(1.5 * sc.tv_u, rel=1e-12)
    assert sc.u_max == pytest.approx(sc.max_u, rel=1e-12)
    assert "tv_bound" in tuning.runner.history_columns(p)


def test_ablation_switch_removes_every_gradient_evaluation(problems, monkeypatch):
    calls = []
    real = search.value_and_grad

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(search, "value_and_grad", counting)
    off = run(problems["ablation"], None)
    assert off.gradient_evaluations == 0 and calls == []  # never traced, never run
    assert off.state.best_feasible  # the start meets its own bounds, at least
    assert off.evaluations == 1 + 4 * (4 + 3)  # the start, then population + line points
    on = run(_with(problems["gradient"], steps=2), None)
    assert on.gradient_evaluations == 2  # one per generation
    assert on.evaluations == 1 + 2 * (4 + 3 + 1)


@pytest.mark.parametrize("which", ["gradient", "ablation"])
def test_each_path_lowers_the_objective_and_resumes_to_the_same_result(problems, which,
                                                                        tmp_path):
    p = problems[which]
    straight = run(_with(p, steps=4), tmp_path / "straight")
    assert straight.state.best_loss < straight.state.start_loss
    first = run(_with(p, steps=2), tmp_path / "resumed")
    assert first.state.iteration == 2
    again = run(_with(p, steps=4), tmp_path / "resumed", resume=True)
    assert again.resumed_from == 2 and again.state.iteration == 4
    np.testing.assert_array_equal(again.state.best_flat, straight.state.best_flat)
    assert again.state.best_loss == straight.state.best_loss
    assert again.state.evaluations == straight.state.evaluations
    meta = json.loads((tmp_path / "resumed" / "checkpoint.json").read_text())
    assert meta["iteration"] == 4 and meta["gradient_evaluations"] == (
        0 if which == "ablation" else 4)


def test_a_nan_is_never_the_best_point_nor_a_direction(problems, monkeypatch):
    assert not search.better(True, float("nan"), False, 1.0)
    assert not search.better(False, float("inf"), False, float("inf"))
    p = problems["gradient"]
    # every gradient is NaN: the line search falls back to random directions, the run goes on
    s = search.Search.open(_with(p, steps=2), None, False, 0.0)
    s.compile()
    real = s.grad
    s.grad = lambda x: (lambda r: (r[0], r[1], jnp.full_like(r[2], jnp.nan)))(real(x))
    # and one candidate of each batch is NaN
    real_batch = s.batch

    def nan_batch(x):
        r = real_batch(x)
        return r | {"loss": r["loss"].at[0].set(jnp.nan)}

    s.batch = nan_batch
    for _ in range(2):
        s.generation()
    assert np.isfinite(s.state.best_loss) and np.all(np.isfinite(s.state.best_flat))
    assert s.state.gradient_evaluations == 2
