"""The box search (`dscjax.search`) on objectives with known answers: a quadratic bowl's
minimum, a box-constrained maximum at a corner, feasibility-first ranking with a hand-made
infeasible region; resumed == uninterrupted, bitwise, for each method (also after a Ctrl-C
inside an iteration); the trace's top points and diverged candidates; the padding of a
single point. Every objective is NumPy: nothing here simulates a closed loop."""

import json

import jax
import numpy as np
import pytest

import dscjax
from dscjax import search
from dscjax.search import CMA, Evaluation, Gradient, Incumbent, Random


class Bowl(search.Problem):
    """loss = |z - c|^2 over the box [lower, upper]; feasible where `feasible(z)` holds;
    `diverged(z)` marks a breakdown (loss +inf)."""

    def __init__(self, c, lower, upper, feasible=None, diverged=None, sign=1.0):
        self.c = np.asarray(c, float)
        self.lower, self.upper = np.asarray(lower, float), np.asarray(upper, float)
        self.feasible, self.diverged, self.sign = feasible, diverged, sign
        self.calls = 0

    def loss(self, z):
        return self.sign * np.sum((z - self.c) ** 2, axis=1) if self.sign > 0 else \
            -np.sum(z, axis=1)

    def evaluate(self, z):
        self.calls += 1
        z = np.asarray(z, float)
        bad = self.diverged(z) if self.diverged else np.zeros(len(z), bool)
        return Evaluation.of(np.where(bad, np.inf, self.loss(z)),
                             self.feasible(z) if self.feasible else None, bad,
                             {"first": z[:, 0]})

    def value_and_grad(self, z):
        z = np.asarray(z, float)
        g = 2 * (z - self.c) if self.sign > 0 else -np.ones_like(z)
        return self.evaluate(z), g

    def sample(self, rng, b):
        return rng.uniform(self.lower, self.upper, (b, len(self.lower)))


C = np.array([0.3, -0.2, 0.5])


def bowl(**kw):
    return Bowl(C, -np.ones(3), np.ones(3), **kw)


@pytest.mark.parametrize("method, tol", [(CMA(), 1e-4), (Gradient(starts=2, screen=8), 1e-2),
                                         (Random(batch=64), 0.25)])
def test_each_method_finds_the_minimum_of_a_bowl(method, tol):
    res = search.run(bowl(), method, x0=np.zeros(3), max_iterations=80)
    assert res.stop_reason == "reached 80 iterations"
    assert res.trace.best_loss < tol ** 2
    np.testing.assert_allclose(res.trace.best_z, C, atol=tol)
    assert res.trace.start_loss == pytest.approx(np.sum(C ** 2), rel=1e-15)


def test_gradient_and_cma_reach_a_maximum_at_a_corner_of_the_box():
    """Maximise sum(z) over [0, 1]^3 (loss -sum z): the projection puts the gradient search
    exactly on the corner; CMA-ES comes within its tolerance of it."""
    p = Bowl(C, np.zeros(3), np.ones(3), sign=-1.0)
    res = search.run(p, Gradient(), x0=np.full(3, 0.5), max_iterations=20)
    np.testing.assert_array_equal(res.trace.best_z, np.ones(3))
    assert res.trace.best_loss == -3.0
    res = search.run(p, CMA(), x0=np.full(3, 0.5), max_iterations=60)
    assert res.trace.best_loss < -3.0 + 1e-3 and np.all(res.trace.best_z <= 1.0)


def test_feasible_points_rank_first_whatever_their_loss():
    """The bowl's minimum lies where z_0 < 0.5, declared infeasible: the incumbent and the top
    points are the best feasible ones (loss >= 0.2^2, at z_0 = 0.5), though infeasible points
    of lower loss were evaluated. (CMA-ES and the gradient move by the loss alone: a caller
    puts its constraints into the loss as penalties, as the tuner does.)"""
    seen = []

    class Seen(Bowl):
        def evaluate(self, z):
            ev = super().evaluate(z)
            seen.extend(ev.loss[~ev.feasible])
            return ev

    p = Seen(C, -np.ones(3), np.ones(3), feasible=lambda z: z[:, 0] >= 0.5)
    tr = search.run(p, Random(batch=64), x0=np.full(3, 0.9), max_iterations=30).trace
    assert tr.best_feasible and tr.best_z[0] >= 0.5
    assert 0.2 ** 2 <= tr.best_loss < 0.06
    assert min(seen) < 0.01  # infeasible points far lower were evaluated
    assert all(r["feasible"] for r in tr.history)  # each iteration's best is a feasible one
    assert tr.top_feasible.all() and np.all(np.diff(tr.top_loss) >= 0)


def test_ranking_and_the_incumbent_by_hand():
    ev = Evaluation.of([3.0, np.nan, 1.0, 2.0, 1.0, -np.inf],
                       [True, True, False, True, False, True])
    # feasible first (3: loss 2, then 0: loss 3), then the infeasible by loss (2 before 4,
    # the earlier of a tie), non-finite last
    assert search.order(ev).tolist() == [3, 0, 2, 4, 1, 5]
    z = np.arange(6.0)[:, None]
    best, i = search.take(Incumbent(), z, ev, 7, 0.0)
    assert (best.loss, best.feasible, best.iteration, i) == (2.0, True, 7, 3)
    assert best.z.tolist() == [3.0]
    # a feasible incumbent is never replaced by an infeasible point of lower loss
    assert search.take(best, z[[2]], ev.rows([2]), 8, 0.0) == (best, None)
    # min_delta: a gain of less than 10 % (relative) replaces the incumbent, without counting
    # as an improvement
    close = Evaluation.of([1.9])
    new, i = search.take(best, np.zeros((1, 1)), close, 9, 0.1)
    assert new.loss == 1.9 and i is None
    assert search.take(best, np.zeros((1, 1)), Evaluation.of([1.7]), 9, 0.1)[1] == 0
    assert search.take(best, np.zeros((1, 1)), Evaluation.of([np.nan]), 9, 0.0) == (best, None)


def _step(z, loss, feasible=None, diverged=None):
    z = np.asarray(z, float)
    return search.Step(z, Evaluation.of(loss, feasible, diverged), None)


def test_the_trace_keeps_the_best_distinct_points_and_the_first_diverged():
    tr = search.Trace("hand", np.zeros(1))
    # 12 candidates, each of 6 points twice (loss 10 - z); then 10 more, diverged from the 5th
    z = np.arange(12)[:, None] % 6
    tr = tr.record(_step(z, 10.0 - z[:, 0]), 1.0, 0.0, 0.0)
    assert tr.top_z[:, 0].tolist() == [5, 4, 3, 2, 1, 0]  # each point once, best first
    assert tr.top_loss.tolist() == [5, 6, 7, 8, 9, 10]
    bad = np.arange(10) >= 4
    tr = tr.record(_step(10.0 + np.arange(10)[:, None], np.where(bad, np.inf, -np.arange(10.0)),
                         diverged=bad), 2.0, 0.5, 0.0)
    assert tr.top_loss.tolist() == [-3, -2, -1, 0, 5, 6, 7, 8]  # the best 8
    assert tr.top_z[:, 0].tolist() == [13, 12, 11, 10, 5, 4, 3, 2]
    assert tr.diverged_z[:, 0].tolist() == [14, 15, 16, 17, 18, 19]
    tr = tr.record(_step(20.0 + np.arange(5)[:, None], np.full(5, np.inf), diverged=np.ones(5)),
                   0.5, 0.0, 0.0)
    assert tr.diverged_z[:, 0].tolist() == [14, 15, 16, 17, 18, 19, 20, 21]  # the first 8
    assert (tr.iterations, tr.evaluations, tr.seconds, tr.compile_seconds) == (3, 27, 3.5, 0.5)
    assert [r["seconds"] for r in tr.history] == [1.0, 3.0, 3.5]
    assert tr.best_loss == -3 and tr.best_z.tolist() == [13.0] and tr.best_iteration == 1
    assert tr.stall == 1  # the third iteration found nothing


METHODS = [CMA(popsize=6), Random(batch=5), Gradient(starts=3, screen=8, coupled=1)]


@pytest.mark.parametrize("method", METHODS, ids=lambda m: m.name)
def test_a_resumed_search_is_the_uninterrupted_one_bitwise(method, tmp_path):
    def go(path, n, resume=False, **kw):
        return search.run(bowl(diverged=lambda z: z[:, 1] > 0.9, **kw), method,
                          x0=np.full(3, 0.2), seed=3, max_iterations=n, path=path,
                          resume=resume, fingerprint={"problem": "bowl"})

    whole = go(tmp_path / "whole.npz", 9)
    first = go(tmp_path / "part.npz", 4)
    assert first.trace.iterations == 4
    # the state file is plain arrays and JSON: nothing that would need a pickle
    with np.load(tmp_path / "part.npz", allow_pickle=False) as z:
        assert all(z[k].dtype.kind in "fiub" for k in z.files)
        assert json.loads(bytes(z["meta"]).decode())["fingerprint"]["caller"] == {
            "problem": "bowl"}
    again = go(tmp_path / "part.npz", 9, resume=True)
    assert again.resumed_from == 4 and again.trace.iterations == 9
    _same(again, whole, method)


def _same(a, b, method):
    ta, tb = a.trace, b.trace
    strip = lambda rows: [{k: v for k, v in r.items() if k != "seconds"} for r in rows]  # noqa
    np.testing.assert_equal(strip(ta.history), strip(tb.history))  # (NaN == NaN here)
    for name in ("best_z", "top_z", "top_loss", "top_feasible", "diverged_z", "start_z"):
        np.testing.assert_array_equal(getattr(ta, name), getattr(tb, name), err_msg=name)
    assert ta.best[1:] == tb.best[1:]  # loss, feasibility, iteration (z above)
    assert (ta.evaluations, ta.gradients, ta.stall, ta.restarts) == (
        tb.evaluations, tb.gradients, tb.stall, tb.restarts)
    sa, sb = method.arrays(a.state), method.arrays(b.state)
    assert sa.keys() == sb.keys()
    for k in sa:
        np.testing.assert_array_equal(sa[k], sb[k], err_msg=k)


@pytest.mark.parametrize("method", METHODS, ids=lambda m: m.name)
def test_ctrl_c_inside_an_iteration_loses_only_that_iteration(method, tmp_path):
    """Ctrl-C while the 5th iteration evaluates (for CMA-ES: between its ask and its tell):
    the state file holds the 4 iterations committed, and resumes to the uninterrupted run."""
    class Interrupted(Bowl):
        def evaluate(self, z):
            if self.calls == self.stop:
                raise KeyboardInterrupt
            return super().evaluate(z)

    def go(path, n, problem, resume=False):
        return search.run(problem, method, x0=np.full(3, 0.2), seed=1, max_iterations=n,
                          path=path, resume=resume)

    whole = go(tmp_path / "whole.npz", 7, bowl())
    counting = bowl()
    go(None, 4, counting)  # the evaluations of 4 iterations
    p = Interrupted(C, -np.ones(3), np.ones(3))
    p.stop = counting.calls
    with pytest.raises(KeyboardInterrupt):
        go(tmp_path / "part.npz", 7, p)
    assert search.load(tmp_path / "part.npz").trace.iterations == 4
    _same(go(tmp_path / "part.npz", 7, bowl(), resume=True), whole, method)


def test_resume_refuses_other_settings_naming_them(tmp_path):
    path = tmp_path / "s.npz"
    search.run(bowl(), CMA(), x0=np.zeros(3), max_iterations=2, path=path, fingerprint={"a": 1})
    with pytest.raises(dscjax.ConfigError) as err:
        search.run(bowl(), CMA(sigma0=0.5), x0=np.zeros(3), max_iterations=3, path=path,
                   resume=True, fingerprint={"a": 1})
    assert str(err.value) == (f"--resume: {path} was made with other settings (settings."
                              f"sigma0 0.3 (now 0.5)); use the same settings, or --overwrite "
                              f"to start afresh")
    np.savez(path, x=np.zeros(2))  # a file of another version
    with pytest.raises(dscjax.ConfigError, match="another version of dscjax"):
        search.run(bowl(), CMA(), x0=np.zeros(3), path=path, resume=True)


def test_limits_and_patience_end_a_search():
    res = search.run(bowl(), Random(batch=7), x0=np.zeros(3), max_evals=20)
    assert (res.trace.evaluations, res.stop_reason) == (21, "reached 20 evaluations")
    # the loss is flat: nothing improves after the start's iteration
    flat = Bowl(C, -np.ones(3), np.ones(3))
    flat.loss = lambda z: np.zeros(len(z))
    res = search.run(flat, Random(batch=2), x0=np.zeros(3), patience=3)
    assert res.trace.iterations == 4 and res.stop_reason.endswith("in 3 iterations")
    res = search.run(bowl(), Random(batch=2), x0=np.zeros(3), time_limit=1e-9)
    assert res.trace.iterations == 1 and res.stop_reason == "time limit 1e-09 s"


@pytest.mark.parametrize("growth", [1, 2])
def test_cma_es_restarts_from_the_start_when_its_criteria_stop_it(monkeypatch, growth):
    """Each restart a fresh CMA-ES from x0; with growth 2 (IPOP) its population doubles: cma's
    4 + floor(3 ln 3) = 7 in three dimensions, then 14, then 28 candidates a generation."""
    import cma

    monkeypatch.setattr(cma.CMAEvolutionStrategy, "stop",
                        lambda self, *a, **k: {"forced": 3} if self.countiter >= 3 else {})
    res = search.run(bowl(), CMA(restarts=2, growth=growth), x0=np.full(3, 0.1), seed=4)
    assert (res.trace.iterations, res.trace.restarts) == (9, 2)
    assert res.stop_reason == "CMA-ES stopped: {'forced': 3}"
    es = res.state.es.es
    np.testing.assert_array_equal(np.asarray(es.x0, float), np.full(3, 0.1))
    assert es.opts["seed"] == int(np.random.SeedSequence([4, 2]).generate_state(1)[0])
    pops = [7 * growth ** r for r in range(3)]
    assert res.trace.evaluations == 1 + 3 * sum(pops) and es.popsize == pops[-1]


def test_cma_es_restarts_when_it_stalls_and_a_resumed_stalling_search_is_the_same(tmp_path):
    """stall = 3: a generation whose instance's best fell by less than stall_gain of it over
    the last 3 generations restarts it. On 1 + |z - c|^2 / 100 (1 to 1.1 on the box) that is
    every instance's 4th generation (2 restarts, then its end); on the bowl from far away
    CMA-ES gains more than 10 % in every 3 generations of its first 12 (no stall there)."""
    flat = Bowl(C, -np.ones(3), np.ones(3))
    flat.loss = lambda z: 1 + np.sum((z - C) ** 2, axis=1) / 100
    method = CMA(restarts=2, stall=3)

    def go(n, path=None, resume=False):
        return search.run(flat, method, x0=np.full(3, 0.1), seed=2, max_iterations=n,
                          path=path, resume=resume)

    whole = go(20)
    assert (whole.trace.iterations, whole.trace.restarts) == (12, 2)
    assert whole.stop_reason == "CMA-ES stopped: {'stall': 3}"
    assert whole.trace.evaluations == 1 + 12 * 7  # cma's 7 candidates in 3 dimensions
    go(6, tmp_path / "s.npz")
    _same(go(20, tmp_path / "s.npz", resume=True), whole, method)
    far = Bowl(np.full(3, 0.9), -np.ones(3), np.ones(3))
    res = search.run(far, CMA(stall=3), x0=np.full(3, -0.9), seed=2, max_iterations=12)
    assert res.trace.restarts == 0


def test_a_replayed_cma_es_continues_exactly_even_from_between_ask_and_tell():
    def make():
        return search.ReplayCMA(np.ones(3), 0.5, {"seed": 3, "verbose": -9, "popsize": 5,
                                                  "randn": np.random.RandomState(3).randn})

    a = make()
    for _ in range(4):
        x = a.ask()
        a.tell(x, (x ** 2).sum(axis=1))
    pending = a.ask()  # asked, never told: the record holds the 4 told generations
    saved = {k: np.array(v) for k, v in a.arrays().items()}
    assert saved["fitness"].shape == (4, 5)
    b = make()
    b.replay(saved)
    np.testing.assert_array_equal(b.ask(), pending)
    with pytest.raises(ValueError, match="replay"):
        make().replay(saved | {"told": saved["told"] + 1.0})


def test_a_single_point_runs_padded_to_a_compiled_width():
    traced = []

    @jax.jit
    def f(z):
        traced.append(z.shape)
        return {"s": z.sum(axis=1)}

    prog = search.Batched(f)
    z = np.arange(12.0).reshape(4, 3)
    assert prog(z)["s"].tolist() == [3, 12, 21, 30]
    assert prog(z[1:2])["s"].tolist() == [12]  # padded to the width 4 compiled
    assert prog(z[:2])["s"].tolist() == [3, 12]  # a batch of its own width
    assert traced == [(4, 3), (2, 3)] and prog.widths == {2, 4} and prog.seconds > 0


def test_a_nan_point_steps_back_from_the_last_good_one_with_half_the_step():
    """The gradient method evaluates a NaN loss and gradient: not accepted, the next point is
    the last good point plus half the step along its own descent direction, and nothing
    non-finite enters the state (Adam's moments stay those of the good point)."""
    class NanSecond(Bowl):
        def value_and_grad(self, z):
            ev, g = super().value_and_grad(z)
            if self.calls == 2:
                return Evaluation.of(np.full(len(z), np.nan)), np.full_like(g, np.nan)
            return ev, g

    p = NanSecond(C, -np.ones(3), np.ones(3))
    method = Gradient()
    ctx = search.Context(0, 0, np.zeros(3))
    one = method.step(p, None, ctx)
    two = method.step(p, one.state, ctx._replace(iteration=1))
    assert one.notes["accepted"] and not two.notes["accepted"]
    s1, s2 = one.state, two.state
    np.testing.assert_array_equal(s2.lr, s1.lr * 0.5)
    np.testing.assert_array_equal(s2.z, np.clip(s1.good_z + s2.lr[:, None] * s1.good_dir,
                                                -1, 1))
    for name in ("good_z", "good_loss", "good_dir", "count", "mu", "nu"):
        np.testing.assert_array_equal(getattr(s2, name), getattr(s1, name), err_msg=name)
    assert all(np.isfinite(x).all() for x in s2)
    # the descent direction is the gradient scaled as Adam scales it, without the momentum
    assert np.all(np.sign(s1.good_dir) == -np.sign(2 * (np.zeros(3) - C)))


@pytest.mark.parametrize("method, tol", [(CMA(), 1e-4), (Gradient(starts=2, screen=8), 1e-2),
                                         (Random(batch=16), 0.05)])
def test_every_method_searches_a_box_of_one_dimension(method, tol, tmp_path):
    """A box of one dimension (pycma 4.5 alone fails on it with 'not yet initialized'):
    each method finds the minimum z = 0.3 of (z - 0.3)^2 on [-1, 1], every candidate inside
    the box; CMA-ES resumes bitwise there too."""
    p = Bowl([0.3], [-1.0], [1.0])
    res = search.run(p, method, x0=np.zeros(1), max_iterations=40)
    assert res.trace.best_z.shape == (1,)
    assert abs(res.trace.best_z[0] - 0.3) < tol
    assert np.all(np.abs(res.trace.top_z) <= 1.0)
    if isinstance(method, CMA):
        whole = search.run(Bowl([0.3], [-1.0], [1.0]), method, x0=np.zeros(1), seed=2,
                           max_iterations=6)
        search.run(Bowl([0.3], [-1.0], [1.0]), method, x0=np.zeros(1), seed=2,
                   max_iterations=3, path=tmp_path / "s.npz")
        again = search.run(Bowl([0.3], [-1.0], [1.0]), method, x0=np.zeros(1), seed=2,
                           max_iterations=6, path=tmp_path / "s.npz", resume=True)
        _same(again, whole, method)
