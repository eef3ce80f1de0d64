"""One pure objective (issue 34): `dscjax.objective` and `tuning.loss_function` give the same
value eagerly and under jit as an eager `simulate`; the README's optax loop lowers its loss;
`simulate` under a trace refuses to refine instead of skipping it silently; specs differing
only in host-side settings share one compiled program."""

import importlib
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import dscjax
import tuning
from dscjax import params
from dscjax.runspec import RunSpec

simulate_module = importlib.import_module("dscjax.simulate")  # dscjax.simulate is the function
README = Path(__file__).resolve().parents[1] / "README.md"


def _readme_loop() -> str:
    """The README's python block that runs an optax optimiser on dscjax.objective."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    loops = [b for b in blocks if "dscjax.objective(" in b and "optax" in b]
    assert len(loops) == 1, "the README shows one optax loop"
    return loops[0]


def test_readme_optax_loop_lowers_the_loss_of_an_eager_simulate():
    code = _readme_loop()
    assert len([line for line in code.splitlines() if line.strip()]) <= 12
    setup = dscjax.paper_example()
    ns = {"jax": jax, "dscjax": dscjax, "optax": optax, "setup": setup}
    exec(compile(code, str(README), "exec"), ns)
    loss, z = ns["loss"], ns["z"]
    paths = list(z)
    # the start: the setup's own numbers, their logs (the block's log=True)
    z0 = {p: jnp.log(jnp.asarray(params.get(setup, p))) for p in paths}
    start, end = float(loss(z0)[0]), float(loss(z)[0])
    assert int(ns["code"]) == 0 and end < 0.9 * start, (start, end)
    # the same figure from an eager simulate of the tuned setup (no refinement needed)
    tuned = params.set_many(setup, {p: jnp.exp(v) for p, v in z.items()})
    spec = RunSpec.make(t_final=2.0)
    ref = dscjax.simulate(tuned, spec=spec).metrics["l2_error_window"]
    np.testing.assert_allclose(end, float(ref), rtol=1e-11)


def test_objective_is_the_same_function_eager_jitted_and_as_simulate():
    # the sampled loop (the README's loop checks the continuous one against simulate)
    setup = dscjax.paper_example()
    spec = RunSpec.make(0.3, 1e-3, sample_time=2e-3, window_start=0.1)
    loss, z0 = dscjax.objective(setup, spec, ["controller.k", "hysteresis.alpha"],
                                "linf_error_window")
    z = {"controller.k": z0["controller.k"] * 1.3, "hysteresis.alpha": z0["hysteresis.alpha"]}
    eager, status = loss(z)
    jitted, _ = jax.jit(loss)(z)
    ref = dscjax.simulate(params.set(setup, "controller.k", z["controller.k"]), spec=spec)
    assert int(status.code) == 0 and int(ref.refinements) == 0
    want = float(ref.metrics["linf_error_window"])
    np.testing.assert_allclose([float(eager), float(jitted)], [want, want], rtol=1e-12)


def test_objective_returns_a_diverged_run_as_its_status():
    # a state bound below the start's state: diverged by the first step, NaN and status 2
    setup = dscjax.paper_example()
    loss, z0 = dscjax.objective(setup, RunSpec.make(0.01, state_bound=1e-9), ["controller.k"])
    value, status = loss(z0)
    assert np.isnan(float(value)) and int(status.code) == 2 and int(status.step) == 1


def test_objective_checks_its_inputs_before_compiling():
    setup = dscjax.paper_example()
    with pytest.raises(dscjax.ConfigError, match="metric must be one of .*'l3_error'"):
        dscjax.objective(setup, RunSpec.make(0.01), ["controller.k"], "l3_error")
    with pytest.raises(dscjax.ConfigError, match="hysteresis.w0 must be > 0 with log=True"):
        dscjax.objective(setup, RunSpec.make(0.01), ["hysteresis.w0"], log=True)


def test_simulate_under_a_trace_refuses_refinement_and_raises_on_divergence():
    setup = dscjax.paper_example()

    def l2(k, **kw):
        s = params.set(setup, "controller.k", k)
        return dscjax.simulate(s, 0.01, 1e-3, throw=False, **kw).metrics["l2_error"]

    k = setup.controller.k
    for traced, arg in ((jax.jit(l2), k), (jax.grad(l2), k), (jax.vmap(l2), jnp.stack([k, k]))):
        with pytest.raises(ValueError, match="refine=6 re-runs a diverged run on the host"):
            traced(arg)
    with pytest.raises(ValueError, match="simulate_batch: refine=6"):
        jax.jit(lambda a: dscjax.simulate_batch(setup, {"hysteresis.alpha": a}, 0.01, 1e-3)
                )(jnp.array([1.0, 1.1]))
    # refine=0 and throw: the divergence check runs inside the compiled function
    spec = RunSpec.make(0.01, state_bound=1e-9, refine=0)
    with pytest.raises(dscjax.DivergenceError):
        dscjax.simulate(setup, spec=spec)
    with pytest.raises(Exception, match="the run diverged"):
        jax.block_until_ready(jax.jit(lambda s: dscjax.simulate(s, spec=spec).x)(setup))


def test_host_settings_do_not_recompile(monkeypatch):
    traces = []
    run = simulate_module.run

    def counted(*args, **kwargs):
        traces.append(args[1])
        return run(*args, **kwargs)

    monkeypatch.setattr(simulate_module, "run", counted)
    setup = dscjax.paper_example()
    t = 0.023  # a step count no other test uses: the first call traces
    specs = [RunSpec.make(t), RunSpec.make(t, refine=0), RunSpec.make(t, device="cpu"),
             RunSpec.make(t, dtype="float32"), RunSpec.make(t, save_every=1, window_start=0.0)]
    assert len({(s.refine, s.device, s.dtype, s.rules) for s in specs}) == len(specs)
    runs = [dscjax.simulate(setup, spec=s) for s in specs]
    assert len(traces) == 1  # one program for all
    for r in runs[1:]:
        np.testing.assert_array_equal(np.asarray(r.x), np.asarray(runs[0].x))


def test_tuning_loss_function_is_the_tuners_loss_eager_and_jitted():
    # J = L2(e on W) / the start's L2(e on W): 1 at the start, the ratio of two eager runs of
    # the loop tuned, the controller sampled at 1 ms
    setup = dscjax.paper_example()
    options = RunSpec.make(0.5, window_start=0.1, sample_time=1e-3)
    cfg = tuning.TuningConfig(
        objective=tuning.ObjectiveSpec(linf=0.0, l2=1.0, u_max=None, tv_max=None,
                                       sampled_weight=0.0),
        robust=tuning.BatchSpec(batch=0), heldout=tuning.BatchSpec(batch=0))
    loss, z0 = tuning.loss_function(tuning.build_problem(setup, options, cfg))
    z = {**z0, "controller.k": z0["controller.k"] + jnp.log(1.5)}
    got = [float(loss(z0)[0]), float(jax.jit(loss)(z)[0])]  # eager, jitted

    def l2(s):
        return float(dscjax.simulate(s, spec=options)
                     .metrics["l2_error_window"])

    ratio = l2(params.set(setup, "controller.k", 1.5 * setup.controller.k)) / l2(setup)
    np.testing.assert_allclose(got, [1.0, ratio], rtol=1e-11)
