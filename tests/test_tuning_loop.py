"""The tuning loop: a short run lowers the objective and writes every file, `--resume`
continues where a run stopped (also after Ctrl-C), a forced NaN is rejected without corrupting
the state, gains.json loads back into `dscjax simulate`.

Small problems (2 s horizon, k_1 and k_2 tuned, 4 held-out plants) keep this file fast; the
problem objects are shared so that each jitted function compiles once.
"""

import json
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dscjax
import tuning
from dscjax.cli.main import main
from dscjax.config import SimOptions
from tuning import checkpoint as ck
from tuning import report as tuning_report
from tuning.runner import run

TINY = """
[simulation]
t_final = 2.0

[tuning]
params = ["controller.k"]

[tuning.optimizer]
name = "adam"
steps = 5
learning_rate = 0.1
save_interval = 2

[tuning.heldout]
batch = 4
"""

FILES = ("gains.json", "history.csv", "report.md", "report.json", "loss_curve.png",
         "before_after.png", "heldout.png", "checkpoint.npz", "checkpoint.json", "best.json")


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory, run_with_config):
    import contextlib
    import io

    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code, out = run_with_config(tmp_path_factory.mktemp("tune"), TINY, "tune", "--quiet")
    (out.parent / "stdout.txt").write_text(stdout.getvalue())
    (out.parent / "stderr.txt").write_text(stderr.getvalue())
    return code, out, out.parent / "config.toml"


def test_the_console_says_what_follows_the_search_and_counts_the_heldout_plants(cli_run):
    code, out, _ = cli_run
    stdout = (out.parent / "stdout.txt").read_text()
    stderr = (out.parent / "stderr.txt").read_text()
    assert code == 0
    assert ("  the held-out check (4 plants, start and tuned gains) and the figures come after "
            "the search; the time limit (100 s) bounds the search only") in stderr
    assert "stopped: reached 5 iterations; 5 iterations" in stdout
    counts = next(line for line in stdout.splitlines() if "held-out batch (4 plants" in line)
    assert re.fullmatch(r"  held-out batch \(4 plants, start -> tuned gains\): tracked \d -> \d; "
                        r"tracked after refinement \(a numerically stiff run re-done with "
                        r"ETDRK4 at a smaller step\) \d -> \d; diverged at every step tried "
                        r"\d -> \d", counts), counts
    heldout = json.loads((out / "report.json").read_text())["heldout"]
    for tag in ("start", "tuned"):
        h = heldout[tag]
        assert h["n_tracked"] + h["n_refined"] + h["n_diverged"] == h["n"] == 4
        assert f"tracked {heldout['start']['n_tracked']} -> {heldout['tuned']['n_tracked']}" \
            in counts
    assert "WARNING" not in stderr or heldout["tuned"]["n_diverged"]
    assert "Plants: tracked " in (out / "report.md").read_text()


def test_short_run_lowers_the_objective_and_writes_every_file(cli_run):
    code, out, _ = cli_run
    assert code == 0
    for name in FILES:
        assert (out / name).stat().st_size > 0, name
    hist = ck.read_history(out / "history.csv")
    assert [r["iteration"] for r in hist] == list(range(5))
    assert min(r["loss"] for r in hist) < hist[0]["loss"]
    report = json.loads((out / "report.json").read_text())
    assert report["run"]["best_loss"] < hist[0]["loss"]
    assert report["nominal"]["tuned"]["smooth_linf_window"] < \
        report["nominal"]["start"]["smooth_linf_window"]
    assert "## Held-out batch: 4 plants" in (out / "report.md").read_text()


def test_gains_json_loads_back_into_simulate(cli_run, tmp_path):
    _, out, _ = cli_run
    code = main(["simulate", "--config", str(out / "gains.json"), "--out", str(tmp_path),
                 "--no-plot"])
    assert code == 0
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    report = json.loads((out / "report.json").read_text())
    tuned = report["nominal"]["tuned"]
    for key in ("linf_error_window", "l2_error", "max_abs_u"):
        assert metrics[key] == pytest.approx(tuned[key], rel=1e-12), key
    gains = json.loads((out / "gains.json").read_text())
    best = json.loads((out / "best.json").read_text())
    assert gains["controller"]["k"] == pytest.approx(best["values"]["controller.k"], rel=1e-15)


def test_existing_run_needs_resume_or_overwrite(cli_run, capsys):
    _, out, cfg = cli_run
    code = main(["tune", "--config", str(cfg), "--out", str(out), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--resume" in err[0] and "Traceback" not in err[0]


@pytest.fixture(scope="module")
def small_problem():
    cfg = tuning.TuningConfig(
        params=("controller.k",),
        optimizer=tuning.OptimizerSpec(name="adam", steps=4, learning_rate=0.1, save_interval=2,
                                       decay_steps=20),
        heldout=tuning.BatchSpec(batch=0))
    return tuning.build_problem(dscjax.paper_example(), SimOptions(t_final=2.0), cfg)


def _with_steps(problem, steps):
    import dataclasses

    cfg = problem.cfg
    new_cfg = dataclasses.replace(cfg, optimizer=dataclasses.replace(cfg.optimizer,
                                                                     steps=steps))
    return dataclasses.replace(problem, cfg=new_cfg)


def test_resume_continues_iterations_and_best(small_problem, tmp_path):
    first = run(small_problem, tmp_path)
    assert int(first.state.iteration) == 4
    best_first = float(first.state.best_loss)
    again = run(_with_steps(small_problem, 7), tmp_path, resume=True)
    assert again.resumed_from == 4
    assert int(again.state.iteration) == 7
    assert float(again.state.best_loss) <= best_first
    hist = ck.read_history(tmp_path / "history.csv")
    assert [r["iteration"] for r in hist] == list(range(7))
    # the uninterrupted run takes the very same steps
    straight = run(_with_steps(small_problem, 7), tmp_path / "straight")
    np.testing.assert_array_equal(np.asarray(straight.state.z["controller.k"]),
                                  np.asarray(again.state.z["controller.k"]))


def test_interrupted_run_keeps_its_best_and_resumes(small_problem, tmp_path):
    def interrupt(row):
        if row["iteration"] == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run(_with_steps(small_problem, 10), tmp_path, progress=interrupt)
    meta = json.loads((tmp_path / "checkpoint.json").read_text())
    assert meta["iteration"] == 3 and meta["stop_reason"] == "interrupted"
    best = json.loads((tmp_path / "best.json").read_text())
    assert best["loss"] == meta["best_loss"]
    again = run(_with_steps(small_problem, 5), tmp_path, resume=True)
    assert again.resumed_from == 3 and int(again.state.iteration) == 5
    assert float(again.state.best_loss) <= best["loss"]


def test_resume_refuses_a_different_problem(small_problem, tmp_path):
    import dataclasses

    run(_with_steps(small_problem, 2), tmp_path)
    assert small_problem.mode == "reverse"  # one plant: the time-parallel reverse mode
    other = dataclasses.replace(small_problem, mode="forward")
    with pytest.raises(dscjax.ConfigError,
                       match=r"other settings \(mode .reverse. \(now .forward.\)\)"):
        run(other, tmp_path, resume=True)


def test_drop_defaults_leaves_out_only_the_keys_at_the_value_given():
    d = {"a": 0, "b": None, "c": "nominal", "d": 3}
    assert ck.drop_defaults(d, {"a": 0, "b": None, "c": "per_plant", "e": 1}) == {
        "c": "nominal", "d": 3}
    assert ck.drop_defaults(d, {}) == d
    assert d == {"a": 0, "b": None, "c": "nominal", "d": 3}  # a new dict: d is left alone


# The keys of each resume fingerprint, written out: an option added later is in it only when
# set away from what older runs did (runs saved before it keep their fingerprint and resume)
OPTIMIZER_KEYS = {"name", "learning_rate", "schedule", "final_lr_fraction", "clip_norm",
                  "gradient", "checkpoint_every", "sigma0", "popsize", "seed", "grad_every",
                  "line_points", "line_min", "line_max", "background_compile"}
OBJECTIVE_KEYS = {"linf", "l2", "effort_l2", "effort_max", "effort_tv", "u_max",
                  "u_max_weight", "tv_max", "tv_max_factor", "tv_max_weight", "sharpness",
                  "u_sharpness", "divergence_penalty", "window_start"}
ADVERSARIAL_KEYS = {"rounds", "disturbance", "ranges", "method", "metric", "search_time",
                    "starts", "batch", "add", "seed"}


def test_fingerprints_carry_a_later_option_only_away_from_its_old_value(small_problem):
    import dataclasses

    from tuning import adversarial
    from tuning.params import Selection

    p, cfg = small_problem, small_problem.cfg

    def described(optimizer=None, objective=None, tune=("controller.k",)):
        new = dataclasses.replace(
            cfg, optimizer=dataclasses.replace(cfg.optimizer, **(optimizer or {})),
            objective=dataclasses.replace(cfg.objective, **(objective or {})))
        return dataclasses.replace(p, cfg=new, selection=Selection.build(p.setup, tune)
                                   ).describe()

    d = described()
    assert set(d["optimizer"]) == OPTIMIZER_KEYS
    assert set(d["objective"]) == OBJECTIVE_KEYS
    k = {"path": "controller.k", "index": None, "transform": "log", "lower": None,
         "upper": None}
    assert d["params"] == [k]
    # line_generations came with a default (50) away from its old behaviour (0: the line in
    # every generation): in the fingerprint of the line methods only, and left out at 0, so
    # that runs saved before it resume with line_generations = 0
    assert described({"name": "cma_path"})["optimizer"]["line_generations"] == 50
    assert "line_generations" not in described({"name": "cma_path", "line_generations": 0}
                                                )["optimizer"]
    assert "line_generations" not in described({"name": "cma"})["optimizer"]
    on = described({"line_backoff": 2}, {"effort_bounds": "per_plant"}, ("controller.k*",))
    assert set(on["optimizer"]) == OPTIMIZER_KEYS | {"line_backoff"}
    assert on["optimizer"]["line_backoff"] == 2
    assert set(on["objective"]) == OBJECTIVE_KEYS | {"effort_bounds"}
    assert on["objective"]["effort_bounds"] == "per_plant"
    assert on["params"] == [k | {"scale": True}]
    for evals, keys in ((None, ADVERSARIAL_KEYS), (8, ADVERSARIAL_KEYS | {"search_evals"})):
        spec = dataclasses.replace(cfg.adversarial, rounds=3, search_evals=evals)
        searched = adversarial.search_problem(
            p.setup, p.options, dataclasses.replace(cfg, adversarial=spec))
        fp = adversarial.run_fingerprint(spec, searched, d)
        assert set(fp) == {"problem", "adversarial"}
        assert set(fp["adversarial"]) == keys
        assert fp["adversarial"]["rounds"] == 0  # more rounds continue the same run
        assert fp["adversarial"].get("search_evals") == evals


def test_forced_nan_is_rejected_without_corrupting_the_state(small_problem):
    problem = small_problem
    opt = problem.cfg.optimizer.make()
    state = tuning.init_state(problem.z0, opt)
    project = problem.selection.project
    aux = {"n_diverged": jnp.asarray(0), "feasible": jnp.asarray(True)}
    grads = {"controller.k": jnp.array([0.3, -0.2])}
    state, rep = tuning.guarded_update(state, jnp.asarray(1.0), aux, grads, opt, project,
                                       0.5, 0.0)
    assert bool(rep["accepted"])
    good = state
    # the next evaluation is NaN (loss and gradient): rejected
    nan_grads = {"controller.k": jnp.array([jnp.nan, 1.0])}
    bad, rep = tuning.guarded_update(good, jnp.asarray(jnp.nan), aux, nan_grads, opt, project,
                                     0.5, 0.0)
    assert not bool(rep["accepted"])
    for tree in (bad.z, bad.good_z, bad.good_grads, bad.best_z, bad.opt_state,
                 bad.good_opt_state):
        for x in jax.tree.leaves(tree):
            assert np.all(np.isfinite(np.asarray(x)))
    assert float(bad.lr_scale) == 0.5
    assert int(bad.n_rejected) == 1 and int(bad.streak) == 1
    assert float(bad.best_loss) == 1.0
    np.testing.assert_array_equal(bad.best_z["controller.k"], good.best_z["controller.k"])
    np.testing.assert_array_equal(bad.good_z["controller.k"], good.good_z["controller.k"])
    # the retried step goes from the last good point along its gradient, half as far
    step_good = np.asarray(good.z["controller.k"] - good.good_z["controller.k"])
    step_bad = np.asarray(bad.z["controller.k"] - good.good_z["controller.k"])
    assert np.all(np.isfinite(step_bad))
    np.testing.assert_allclose(step_bad, 0.5 * step_good, rtol=1e-12)
    # a later good evaluation is accepted again
    state, rep = tuning.guarded_update(bad, jnp.asarray(0.9), aux, grads, opt, project, 0.5,
                                       0.0)
    assert bool(rep["accepted"]) and float(state.best_loss) == 0.9


def test_more_divergence_is_rejected(small_problem):
    opt = small_problem.cfg.optimizer.make()
    state = tuning.init_state(small_problem.z0, opt)
    grads = {"controller.k": jnp.array([0.3, -0.2])}
    ok = {"n_diverged": jnp.asarray(0), "feasible": jnp.asarray(True)}
    state, _ = tuning.guarded_update(state, jnp.asarray(1.0), ok, grads, opt,
                                     small_problem.selection.project, 0.5, 0.0)
    worse = {"n_diverged": jnp.asarray(1), "feasible": jnp.asarray(False)}
    state, rep = tuning.guarded_update(state, jnp.asarray(0.5), worse, grads, opt,
                                       small_problem.selection.project, 0.5, 0.0)
    assert not bool(rep["accepted"]) and float(state.best_loss) == 1.0


class _Member:
    """An objective with known losses and aux (no simulation): what `Combined` reduces."""

    def __init__(self, loss, linf, n_div, feasible, batch):
        self.loss, self.linf, self.n_div, self.feasible, self.batch_size = (
            loss, linf, n_div, feasible, batch)

    def evaluate(self, z, overrides=None, checkpoint_every=None):
        return jnp.asarray(self.loss * z), {
            "terms": {"linf": jnp.asarray(2 * self.loss)}, "linf_window": jnp.asarray(self.linf),
            "max_abs_u": jnp.asarray(self.linf + 1), "n_diverged": jnp.asarray(self.n_div),
            "feasible": jnp.asarray(self.feasible)}


def test_combined_objective_is_the_mean_or_max_of_its_members():
    members = (_Member(1.0, 0.5, 0, True, 3), _Member(4.0, jnp.nan, 2, False, 5))
    for how, expect in (("mean", 2.5), ("max", 4.0)):
        obj = tuning.Combined(members, how)
        loss, aux = obj.evaluate(jnp.asarray(2.0))
        assert float(loss) == 2 * expect and float(aux["terms"]["linf"]) == 2 * expect
        assert float(aux["linf_window"]) == 0.5 and float(aux["max_abs_u"]) == 1.5
        assert int(aux["n_diverged"]) == 2 and not bool(aux["feasible"])
        assert obj.batch_size == 8
    with pytest.raises(dscjax.validation.ConfigError, match="combine must be one of"):
        tuning.Combined(members, "sum")


def test_combine_refuses_problems_that_tune_other_parameters(small_problem):
    import dataclasses

    other = dataclasses.replace(small_problem, selection=tuning.Selection.build(
        small_problem.setup, ["controller.tau"]))
    with pytest.raises(dscjax.validation.ConfigError, match="same parameters"):
        tuning.combine([small_problem, other])
    both = tuning.combine([small_problem, small_problem], "max")
    assert both.members == (small_problem, small_problem)
    assert both.describe()["combine"] == "max" and len(both.describe()["members"]) == 2
    z = both.selection.init(both.setup)
    with pytest.raises(dscjax.validation.ConfigError, match="combined problem"):
        tuning_report.evaluate(both, z, z)  # one line, not an AttributeError
