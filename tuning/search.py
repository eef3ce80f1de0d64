"""CMA-ES ("cma"), CMA-ES with a line search from the incumbent along CMA-ES's own evolution
path ("cma_path", the default of `dscjax tune`), along random directions ("cma_line") or along
the exact gradient ("cma_grad"), one batched simulation per generation.

"cma" is steps 1 and 3 below alone: the `cma` package's CMA-ES in the tuner's coordinates z,
the population simulated as one batch, the best point ranked feasible first, then by loss.
"cma_line" is "cma_grad" with the gradient switched off (random directions in step 2).
"cma_path" takes, in step 2, the direction of CMA-ES's evolution path p_c (the smoothed
shift of its mean over recent generations, which CMA-ES keeps for its rank-one update), scaled
to unit Mahalanobis length: the line extrapolates the progress CMA-ES has been making, up to
sigma sqrt(n) beyond the incumbent, and a winner injected into CMA-ES lengthens the path in
turn (a momentum). No extra state: p_c is part of the replayed CMA-ES. While p_c is zero
(the first generation) or not finite, the direction is random, as in cma_line.

Every generation:

1. CMA-ES (the `cma` package, in the tuner's coordinates z) asks for its population.
2. Gradient component (every `grad_every` generations; 0 switches it off, the ablation): the
   exact gradient g of the loss at the incumbent (the best point so far, feasible first) in
   the AD mode of the problem, and `line_points` candidates x_best + a_j d along the
   direction d = -C g / sqrt(g' C g) preconditioned by CMA-ES's own covariance C (the metric
   CMA-ES has learnt; unit Mahalanobis length), with step sizes a_j = sigma sqrt(n) x
   geomspace(line_min, line_max): a line search whose points are simulated in the same batch
   as the population, so it costs about one extra slice of the batch, not one run each.
3. The population and the line points: ONE batched simulation (`batch_fn`).
4. CMA-ES is told its population; the best line point, when it beats the incumbent, is
   injected into the next generation (so CMA-ES moves its mean towards it).

`line_backoff = m` (0: off, the default) skips the line while it keeps losing: after k
consecutive generations whose line did not win, the next min(2^(k-1), m) generations are
steps 1, 3 and 4 alone, CMA-ES's population in a second compiled program of that width; a
winning line resets k. Measured on the robust problem (docs/tuning.md, round 4): it keeps
most of the line's wins at about half its cost, but did not beat CMA-ES at equal wall time.

`line_generations = N` (0: every generation) takes the line in the first N generations only
and leaves CMA-ES alone after them (steps 1, 3 and 4, its population in a second program of
that width, compiled when first needed). Measured on the robust problem (docs/tuning.md,
round 6): the injected line helps CMA-ES's first generations and then keeps it from
converging as deep as its own updates do; switched off after N = 50 generations, its median
over 12 seeds is below CMA-ES's, though it wins only about half of the paired rounds.

Why this shape (measured, docs/tuning.md): one exact gradient costs about as much as one
CMA-ES generation, and on this kinked landscape (sat, |u'|, the running max, two active
constraints) a plain gradient step often raises the loss a short way off; evaluating many step
sizes at once and keeping the best makes the gradient's information safe to use, and CMA-ES
keeps exploring. With the gradient off the same loop is CMA-ES alone (the ablation).

State (`SearchState`): the CMA-ES (`dscjax.cmaes.ReplayCMA`, which records the fitness told
and the point injected per generation), the incumbent, the counters (the back-off's and the
line's wins per step size included) and the generator of the random line directions. No
pickle: ONE atomic `search.npz` holds the recorded fitness and injections, the last
population, the incumbent (float64, bitwise), the counters and the generator's state
(uint64 words). A resumed run rebuilds CMA-ES with the same seed and options and replays
ask/tell/inject with the stored values (no simulation), so it continues exactly where it
stopped (tested: resumed == uninterrupted, bitwise).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from dscjax import files, params, xla
from dscjax.cmaes import ReplayCMA
from dscjax.progress import critical
from tuning import checkpoint as ck
from tuning.objective import aggregate, plant_loss, simulate_metrics, within_bounds
from tuning.optimize import value_and_grad

STATE_FILE = "search.npz"
# SearchState's numbers in STATE_FILE beside the CMA-ES record (one atomic file: the whole
# state or the previous one, never a mix)
_COUNTERS = ("best_feasible", "best_iteration", "iteration", "evaluations",
             "gradient_evaluations", "line_wins", "first_grad", "stall")
# the line's back-off (`line_backoff`); absent from the files of older runs, which had none
_BACKOFF = ("line_losses", "line_skip")
# SearchState.line_step_wins, (line_points,) int64; absent from older files (zeros then)
_STEP_WINS = "line_step_wins"
_FLOATS = ("best_loss", "start_loss")


def batch_fn(problem):
    """Jitted (B, n) flat z -> per-candidate loss, feasibility, exact figures and terms: the
    same loss as the gradient method's (J of the nominal plant or the aggregate over the
    training batch), every candidate (x every training plant) as one batched simulation."""
    obj = problem.objective
    _, unravel = ravel_pytree(problem.z0)
    columns = obj.selection.columns(obj.setup)
    train = obj.overrides or {}
    n_train = obj.batch_size if train else 1
    sc = obj.scales

    # one top-level batched program: 512-bit vectors where the CPU has them (dscjax.xla)
    @functools.partial(jax.jit, compiler_options=xla.compiler_options())
    def run(flat_pts):
        table = jax.vmap(lambda p: obj.selection.row(unravel(p)))(flat_pts)
        b = flat_pts.shape[0]
        ov = params.overrides(obj.setup, columns, table)
        if train:
            ov = {p: jnp.repeat(v, n_train, axis=0) for p, v in ov.items()}
            ov |= {p: jnp.tile(jnp.asarray(v), (b,) + (1,) * (np.ndim(v) - 1))
                   for p, v in train.items()}
        m, div = simulate_metrics(obj.setup, obj.sim, obj.extra(), ov)
        # the training plants' own bounds (per_plant), laid out as the plants are: tiled
        bounds = sc.bounds(train=bool(train), tile=b)
        loss, terms = plant_loss(m, div, obj.spec, sc, len(obj.requirements), bounds)
        feas = ~div & within_bounds(m, bounds)
        for i in range(len(obj.requirements)):
            feas = feas & (m[f"req{i}_met"] > 0)

        def per(v, how):
            v = v.reshape(b, n_train)
            return jax.vmap(lambda r: aggregate(r, how, obj.cvar_level))(v) if train \
                else v[:, 0]

        def worst(v):  # max over the plants that did not diverge (NaN: none)
            v = jnp.where(div, -jnp.inf, v).reshape(b, n_train).max(axis=1)
            return jnp.where(jnp.isfinite(v), v, jnp.nan)

        return {"loss": per(loss, obj.aggregate),
                "feasible": feas.reshape(b, n_train).all(axis=1),
                "n_diverged": div.reshape(b, n_train).sum(axis=1),
                "linf_window": worst(m["linf_error_window"]),
                "max_abs_u": worst(m["max_abs_u"]), "tv_u": worst(m["tv_u"]),
                "terms": {k: per(jnp.where(div, 0.0, v), obj.aggregate)
                          for k, v in terms.items()}}

    return run


def grad_fn(problem):
    """Jitted flat z -> (loss, feasible, flat gradient), exact, in the problem's AD mode."""
    obj = problem.objective
    _, unravel = ravel_pytree(problem.z0)

    @jax.jit
    def run(flat):
        (loss, aux), g = value_and_grad(obj, unravel(flat), problem.mode,
                                        obj.sim.checkpoint_every)
        return loss, aux["feasible"], ravel_pytree(g)[0]

    return run


def z_box(problem) -> tuple[np.ndarray, np.ndarray]:
    """The box of the flat z (the order of `ravel_pytree(problem.z0)`)."""
    return problem.selection.z_box(problem.z0)


def better(feas_a, loss_a, feas_b, loss_b) -> bool:
    """Is (feas_a, loss_a) better than (feas_b, loss_b)? Feasible first, then loss."""
    if not np.isfinite(loss_a):
        return False
    return bool((feas_a and not feas_b) or (feas_a == feas_b and loss_a < loss_b))


@dataclasses.dataclass
class SearchState:
    """What the loop carries; the report reads the same names as a `TuneState`'s."""

    cma: ReplayCMA  # CMA-ES and what it was told (its random stream: opts["randn"])
    best_flat: np.ndarray  # (n,) incumbent in flat z
    best_loss: float = math.inf
    best_feasible: bool = False
    best_iteration: int = -1
    iteration: int = 0  # generations done
    evaluations: int = 0  # loss evaluations (candidates), the gradient's own included
    gradient_evaluations: int = 0
    line_wins: int = 0  # generations whose best line point beat the incumbent
    # (line_points,) int64: of those, the generations each step size won (0: the shortest)
    line_step_wins: np.ndarray = dataclasses.field(
        default_factory=lambda: np.zeros(0, np.int64))
    first_grad: int = -1  # generation of the first gradient (-1: none yet)
    start_loss: float = math.nan  # the loss at the start point
    rng: Any = None  # np.random.Generator of the random line directions
    stall: int = 0
    line_losses: int = 0  # consecutive generations whose line did not win (line_backoff)
    line_skip: int = 0  # generations left before the line is taken again (line_backoff)
    restarts: int = 0  # fresh CMA-ES instances started after cma's own criteria stopped one
    start_flat: np.ndarray | None = None  # (n,) the start point: every CMA-ES instance's x0
    n_rejected: int = 0  # (no steps are rejected; kept for the report)
    unravel: Any = None

    @property
    def es(self):  # the cma.CMAEvolutionStrategy
        return self.cma.es

    @property
    def best_z(self):
        return jax.tree.map(np.asarray, self.unravel(jnp.asarray(self.best_flat)))


def new_state(problem, spec, z_init=None) -> SearchState:
    """A fresh search from z_init (default problem.z0): CMA-ES's mean and the incumbent."""
    flat0, unravel = ravel_pytree(problem.z0)
    if z_init is not None:
        flat0 = ravel_pytree({k: jnp.asarray(z_init[k]) for k in problem.z0})[0]
    flat0 = np.asarray(flat0, float)
    return SearchState(cma=new_cma(problem, spec, flat0), best_flat=flat0, unravel=unravel,
                       start_flat=flat0.copy(),
                       rng=np.random.default_rng(spec.seed + 2),
                       line_step_wins=np.zeros(line_points(spec), np.int64))


def new_cma(problem, spec, x0, restart: int = 0) -> ReplayCMA:
    """CMA-ES from x0: sigma0, the box, the population, and the seed spec.seed + 1 (restart
    r > 0: a seed drawn from SeedSequence([seed, r]), so that no restart replays the stream
    of a run with another seed)."""
    lo, hi = z_box(problem)
    seed = (spec.seed + 1 if not restart else
            int(np.random.SeedSequence([spec.seed, restart]).generate_state(1)[0]))
    opts = {"seed": seed, "verbose": -9, "randn": np.random.RandomState(seed).randn,
            "bounds": [[x if np.isfinite(x) else None for x in lo],
                       [x if np.isfinite(x) else None for x in hi]]}
    if spec.popsize:
        opts["popsize"] = spec.popsize
    return ReplayCMA(np.asarray(x0, float), spec.sigma0, opts)


def line_points(spec) -> int:
    """Points of the line search per generation: `line_points`, none for "cma"."""
    return spec.line_points if spec.name != "cma" else 0


@dataclasses.dataclass
class Search:
    """One invocation of the cma_grad loop (the counterpart of runner._Loop)."""

    problem: Any
    spec: Any  # OptimizerSpec
    state: SearchState
    history: list[dict]
    out: Path | None
    t_start: float
    elapsed_before: float = 0.0
    resumed_from: int = 0
    compile_s: float = 0.0
    last_iter_s: float = 0.0
    batch: Any = None  # the compiled batch of `width` candidates
    # the one of CMA-ES's population alone (line_backoff, line_generations)
    pop_batch: Any = None
    grad: Any = None

    def __post_init__(self):
        self._jitted = batch_fn(self.problem)
        points = line_points(self.spec)
        self.grad = grad_fn(self.problem) if (self.spec.name == "cma_grad"
                                               and self.spec.grad_every and points) else None
        self.lo, self.hi = z_box(self.problem)
        n = self.state.best_flat.size
        self.steps = math.sqrt(n) * np.geomspace(self.spec.line_min, self.spec.line_max,
                                                 points) if points else np.zeros(0)

    @property
    def width(self) -> int:
        return self.state.es.popsize + self.steps.size

    @property
    def _backoff(self) -> bool:
        return bool(self.spec.line_backoff and self.steps.size)

    @property
    def _line_over(self) -> bool:
        """Has a line method passed its `line_generations` (no line from here on)?"""
        n = self.spec.line_generations
        return bool(self.steps.size and n and self.state.iteration >= n)

    def restart(self) -> None:
        """CMA-ES's own termination criteria fired (`es.stop()`: converged or stuck) with
        budget left: a fresh, independent CMA-ES from the start point (sigma0, the same
        population, a seed of its own). Not from the incumbent: where CMA-ES stops early the
        incumbent is typically on a cliff edge, every sample around it diverging alike
        (flat fitness; measured: 9 of 11 points 1e-4 away in z). The incumbent, counters and
        history carry on, so the best point of all the restarts is the result."""
        st = self.state
        st.restarts += 1
        st.stall = 0  # `patience` generations for the fresh CMA-ES to beat the incumbent
        st.cma = new_cma(self.problem, self.spec, st.start_flat, st.restarts)

    def _line_now(self) -> bool:
        """Is the line taken in this generation? Always, unless `line_backoff` skips it
        after lines that lost (see `_after_line`) or `line_generations` have passed."""
        return bool(self.steps.size) and self.state.line_skip == 0 and not self._line_over

    def _after_line(self, taken: bool, won: bool) -> None:
        """line_backoff = m > 0: after k consecutive losing lines the line is skipped for
        min(2^(k-1), m) generations (CMA-ES's population alone, its own batch width); a
        win resets k. A skipped generation counts down."""
        st, m = self.state, self.spec.line_backoff
        if not self._backoff:
            return
        if not taken:  # (after line_generations: for good, the countdown stays at 0)
            st.line_skip = max(st.line_skip - 1, 0)
        elif won:
            st.line_losses = 0
        else:
            st.line_losses += 1
            st.line_skip = min(2 ** (st.line_losses - 1), m)

    def compile(self) -> None:
        """Compile the batched simulation now and the gradient now or, with
        `background_compile`, in a thread while the first generations run (their line
        points then take random directions, as in the ablation). Both count in wall time.
        Compiled programs are kept in the objective's cache (`Objective.compiled`), so that a
        run resumed in the same process does not compile again."""
        t0 = time.perf_counter()
        cache = self.problem.objective.compiled
        # a run resumed after line_generations needs neither the line's width nor the
        # gradient; line_backoff needs the population's width now (line_generations: when
        # first needed, see `generation`)
        over = self._line_over
        self.batch = None if over else self._program(self.width)
        self.pop_batch = (self._program(self.state.es.popsize) if self._backoff or over
                          else None)
        if over:
            self.grad = None
        if self.grad is not None:
            key = ("cma_grad gradient", self.problem.mode)
            if key in cache:
                self.grad = cache[key]
            elif self.spec.background_compile and self.state.first_grad < 0:
                # (A resumed run that already used the gradient compiles it at once, so that
                # it continues exactly as the uninterrupted run did.)
                import concurrent.futures

                lowered = self.grad.lower(jnp.asarray(self.state.best_flat))
                self._pool = concurrent.futures.ThreadPoolExecutor(1)
                self.grad = self._pool.submit(lowered.compile)
            else:
                cache[key] = self.grad.lower(jnp.asarray(self.state.best_flat)).compile()
                self.grad = cache[key]
        self.compile_s = time.perf_counter() - t0

    def _gradient(self):
        """The compiled gradient, or None while it is still compiling."""
        g = self.grad
        if g is None:
            return None
        if hasattr(g, "done"):
            if not g.done():
                return None
            self.grad = g = g.result()
            self.problem.objective.compiled[("cma_grad gradient", self.problem.mode)] = g
            self._pool.shutdown()
        return g

    def generation(self) -> dict:
        st, es, spec = self.state, self.state.es, self.spec
        t_it = time.perf_counter()
        if st.iteration == 0 and st.evaluations == 0:
            # The start point is part of every method's history: evaluated once, padded to
            # the batch width so that no other program is compiled.
            n = es.popsize if self._backoff else self.width
            res = self._eval(np.tile(st.best_flat, (n, 1)), 1)
            st.start_loss = float(res[0][0])
            self._take(st.best_flat[None, :], *res)
        pop = st.cma.ask()
        pts = [pop]
        base = st.best_flat
        grad_norm = float("nan")
        take_line = self._line_now()
        compiled_s = 0.0
        if not take_line and self.pop_batch is None and self.width != es.popsize:
            # line_generations: the population's program, compiled when first needed; its
            # time is compilation (compile_s), not the generation's own (last_iter_s)
            t0 = time.perf_counter()
            self.pop_batch = self._program(es.popsize)
            compiled_s = time.perf_counter() - t0
            self.compile_s += compiled_s
        if take_line:
            cov = es.sm.covariance_matrix
            d = None
            grad = self._gradient() if st.iteration % max(spec.grad_every, 1) == 0 else None
            if grad is not None:
                if st.first_grad < 0:
                    st.first_grad = st.iteration
                _, _, g = grad(jnp.asarray(base))
                g = np.asarray(g, float)
                st.gradient_evaluations += 1
                st.evaluations += 1
                grad_norm = float(np.linalg.norm(g))
                cg = cov @ g
                scale = math.sqrt(max(float(g @ cg), 0.0))
                if np.all(np.isfinite(g)) and scale > 0:  # never a non-finite direction
                    d = -cg / scale
            if d is None and spec.name == "cma_path":
                d = _path_direction(es, cov)
            if d is None:  # no gradient (off, compiling, skipped): a random direction of
                # unit Mahalanobis length under CMA-ES's covariance
                xi = st.rng.standard_normal(base.size)
                d = np.linalg.cholesky(cov + 1e-300 * np.eye(base.size)) @ (
                    xi / np.linalg.norm(xi))
            line = base[None, :] + es.sigma * self.steps[:, None] * d[None, :]
            pts.append(np.clip(line, self.lo, self.hi))
        x = np.concatenate(pts)
        res = self._eval(x, x.shape[0])
        loss = res[0]
        k = pop.shape[0]
        st.cma.tell(pop, np.where(np.isfinite(loss[:k]), loss[:k], 1e30))
        improved = self._take(x, *res)
        won = bool(take_line and improved and improved[0] >= k)
        if won:
            st.line_wins += 1
            st.line_step_wins[improved[0] - k] += 1
            if spec.line_inject:
                st.cma.inject(st.best_flat)
        self._after_line(take_line, won)
        i = int(np.argmin(np.where(np.isfinite(loss), loss, np.inf)))
        terms = {name: float(v[i]) for name, v in res[-1].items()}
        st.iteration += 1
        st.stall = 0 if improved else st.stall + 1
        self.last_iter_s = time.perf_counter() - t_it - compiled_s
        row = {"iteration": st.iteration - 1, "loss": float(loss[i]), "accepted": True,
               "feasible": bool(res[1][i]), "best_loss": st.best_loss, "lr": float(es.sigma),
               "grad_norm": grad_norm, "linf_window": float(res[3][i]),
               "max_abs_u": float(res[4][i]), "n_diverged": int(res[2][i]), **terms,
               "wall_s": self.elapsed_before + time.perf_counter() - self.t_start,
               "best_iteration": st.best_iteration, "best_feasible": st.best_feasible}
        self.history.append(row)
        return row

    def _program(self, w: int):
        """The batch of w candidates, compiled once per objective (`Objective.compiled`)."""
        cache = self.problem.objective.compiled
        key = ("cma_grad batch", w)
        if key not in cache:
            x = jnp.asarray(np.tile(self.state.best_flat, (w, 1)))
            cache[key] = self._jitted.lower(x).compile()
        return cache[key]

    def _eval(self, x, n_used):
        program = self.batch if x.shape[0] == self.width else self.pop_batch
        r = jax.device_get(program(jnp.asarray(x)))
        self.state.evaluations += n_used
        return (np.asarray(r["loss"], float)[:n_used], np.asarray(r["feasible"])[:n_used],
                np.asarray(r["n_diverged"])[:n_used], np.asarray(r["linf_window"])[:n_used],
                np.asarray(r["max_abs_u"])[:n_used],
                {k: np.asarray(v)[:n_used] for k, v in r["terms"].items()})

    def _take(self, x, loss, feas, *_):
        """Replace the incumbent by the best of x if better; returns [index] or []."""
        st = self.state
        best = None
        for i in range(loss.shape[0]):
            cur = (st.best_feasible, st.best_loss) if best is None else (feas[best],
                                                                           loss[best])
            if better(bool(feas[i]), float(loss[i]), bool(cur[0]), float(cur[1])):
                best = i
        if best is None:
            return []
        margin = self.spec.min_delta * abs(st.best_loss) if np.isfinite(st.best_loss) else 0
        real = (bool(feas[best]) and not st.best_feasible) or loss[best] < st.best_loss - margin
        st.best_flat = np.array(x[best], float)
        st.best_loss, st.best_feasible = float(loss[best]), bool(feas[best])
        st.best_iteration = st.iteration
        return [best] if real else []

    # -- files -----------------------------------------------------------------------------
    def save(self, stop_reason: str | None = None) -> None:
        """Write every checkpoint file, a Ctrl-C waiting for them (dscjax.progress): the
        history and the best point, then the state (STATE_FILE), then checkpoint.json, so
        that a save cut short (a full disk) leaves a state whose history is on disk."""
        if self.out is None:
            return
        with critical():
            self._save(stop_reason)

    def _save(self, stop_reason: str | None) -> None:
        from tuning.runner import history_columns, write_best

        st = self.state
        ck.write_history(self.out / "history.csv", self.history,
                         history_columns(self.problem))
        write_best(self.out, self.problem, st)
        files.write_npz(self.out / STATE_FILE, st.cma.arrays() | {
            "best_flat": st.best_flat, "start_flat": st.start_flat,
            "line_rng": _rng_words(st.rng)}
            | {k: np.float64(getattr(st, k)) for k in _FLOATS}
            | {k: np.int64(getattr(st, k)) for k in _COUNTERS + _BACKOFF}
            | {_STEP_WINS: st.line_step_wins, "restarts": np.int64(st.restarts)})
        desc = self.problem.describe()
        files.write_json(self.out / "checkpoint.json", {
            "version": ck.FORMAT_VERSION, "fingerprint": ck.fingerprint(desc),
            "iteration": st.iteration, "best_loss": st.best_loss,
            "best_iteration": st.best_iteration, "best_feasible": st.best_feasible,
            "evaluations": st.evaluations, "gradient_evaluations": st.gradient_evaluations,
            "elapsed_total_s": self.elapsed_before + time.perf_counter() - self.t_start,
            "stop_reason": stop_reason,
            "state": {"kind": "cma_grad", "file": STATE_FILE},
            "problem": desc})

    @classmethod
    def open(cls, problem, out: Path | None, resume: bool, t_start: float,
             z_init=None) -> Search:
        """A fresh search from z_init (default the start gains), or the one saved in out."""
        spec = problem.cfg.optimizer
        state = new_state(problem, spec, z_init)
        history: list[dict] = []
        elapsed = 0.0
        resumed = 0
        if resume:
            meta = files.read_json(out / "checkpoint.json")
            files.check_same(meta.get("problem"), problem.describe(),
                             where=f"the checkpoint in {out}",
                             fix="start afresh with --overwrite or another --out")
            _restore(state, files.read_npz(out / STATE_FILE), out,
                     functools.partial(new_cma, problem, spec))
            history = [r for r in ck.read_history(out / "history.csv")
                       if r["iteration"] < state.iteration]
            elapsed = float(meta.get("elapsed_total_s", 0.0))
            resumed = state.iteration
        return cls(problem, spec, state, history, out, t_start, elapsed, resumed)


def _path_direction(es, cov) -> np.ndarray | None:
    """CMA-ES's evolution path p_c (its smoothed recent mean shift), scaled to unit
    Mahalanobis length under C; None while it is still zero or not finite."""
    pc = np.asarray(es.pc, float)
    q = float(pc @ np.linalg.solve(cov, pc)) if np.all(np.isfinite(pc)) else 0.0
    return pc / math.sqrt(q) if np.isfinite(q) and q > 0 else None


def _restore(state: SearchState, arrays: dict | None, out: Path, cma=None) -> None:
    """Bring a fresh state to the saved one: replay CMA-ES (the instance of the last restart,
    built by `cma(x0, restart)` from the saved start point), set counters and generator."""
    from dscjax.validation import ConfigError

    fix = "start afresh with --overwrite or another --out"
    if arrays is None or any(k not in arrays for k in _COUNTERS + _FLOATS):
        raise ConfigError(f"--resume: {out / STATE_FILE} is missing or unreadable; {fix}")
    state.restarts = int(arrays.get("restarts", 0))  # (0 in files from before restarts)
    if "start_flat" in arrays:  # (older files: the z_init or z0 new_state was given)
        state.start_flat = np.array(arrays["start_flat"], float)
        state.cma = cma(state.start_flat, state.restarts)
    try:
        state.cma.replay(arrays)
    except ValueError as e:
        raise ConfigError(f"--resume: {e} (another cma version?); {fix}") from None
    for k in _COUNTERS:
        setattr(state, k, type(getattr(state, k))(arrays[k]))
    for k in _BACKOFF:  # (0 in the files of runs from before line_backoff)
        setattr(state, k, int(arrays.get(k, 0)))
    # (zeros in the files of runs from before the count)
    state.line_step_wins = np.array(arrays.get(_STEP_WINS, state.line_step_wins), np.int64)
    for k in _FLOATS:
        setattr(state, k, float(arrays[k]))
    state.best_flat = np.array(arrays["best_flat"], float)
    _set_rng_words(state.rng, arrays["line_rng"])


def _rng_words(rng: np.random.Generator) -> np.ndarray:
    """PCG64's state as uint64 words: state and increment (128 bits each, high word first),
    has_uint32, uinteger."""
    st = rng.bit_generator.state
    words = []
    for k in ("state", "inc"):
        v = int(st["state"][k])
        words += [v >> 64, v & (2**64 - 1)]
    return np.asarray(words + [st["has_uint32"], st["uinteger"]], dtype=np.uint64)


def _set_rng_words(rng: np.random.Generator, words) -> None:
    w = [int(x) for x in words]
    st = rng.bit_generator.state
    rng.bit_generator.state = st | {
        "state": {"state": (w[0] << 64) | w[1], "inc": (w[2] << 64) | w[3]},
        "has_uint32": w[4], "uinteger": w[5]}
