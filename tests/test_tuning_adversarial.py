"""Min-max tuning (`dscjax tune --adversarial R`, issue 14): one round on a 0.4 s horizon with
one tuned gain and random-sampling searches of 0.3 s, run once for the module through the CLI;
then what it wrote, a resume that redoes nothing, and the errors of bad values."""

import dataclasses
import json
import shutil
import tomllib

import numpy as np
import pytest
from compilations import counted

import dscjax
import tuning
from dscjax import config, files, worst
from dscjax.cli.main import main
from dscjax.runspec import RunSpec
from tuning import adversarial, runner

TOML = """
[simulation]
t_final = 0.4
window_start = 0.2

[tuning]
params = ["controller.k"]

[tuning.optimizer]
steps = 2

[tuning.robust]
batch = 2
aggregate = "max"

[tuning.heldout]
batch = 0

[tuning.adversarial]
disturbance = "fourier:2:0.3"
method = "random"
search_time = 0.3
batch = 4
"""


@pytest.fixture(scope="module")
def adv_run(tmp_path_factory, run_with_config):
    return run_with_config(tmp_path_factory.mktemp("adv"), TOML, "tune", "--adversarial", "1",
                           "--quiet", "--no-plot")


def test_one_round_writes_fresh_worst_cases_of_start_and_tuned_gains(adv_run):
    code, out = adv_run
    assert code == 0
    rep = json.loads((out / "report.json").read_text())
    adv = rep["adversarial"]
    assert [r["round"] for r in adv["rounds"]] == [1]
    fresh = adv["fresh"]
    assert fresh["start"]["seed"] == fresh["tuned"]["seed"] == adversarial.FRESH_SEED
    assert "Fresh worst-case search" in (out / "report.md").read_text()
    # each fresh worst value is that of `simulate` on its gains, plant and waveform, in the
    # loop tuned (the controller sampled at 1 ms)
    for tag, gains in (("start", None), ("tuned", out / "gains.json")):
        f = fresh[tag]
        setup = dscjax.paper_example()
        if gains is not None:
            setup, _ = config.from_dict(config.read(gains))
        spec = worst.DisturbanceSpec.parse("fourier:2:0.3")
        setup = setup.replace(plant=dataclasses.replace(
            setup.plant, disturbance=spec.model(f["disturbance"]["coefficients"], 0.4)))
        setup = dscjax.params.set_many(setup, f["parameters"])
        traj = dscjax.simulate(setup, 0.4, 1e-3, window_start=0.2, sample_time=1e-3)
        assert f["value"] == pytest.approx(float(traj.metrics["linf_error_window"]), rel=1e-12)
        assert abs(f["disturbance"]["coefficients"][0]) <= 0.3


def test_the_round_adds_its_worst_cases_to_the_training_set(adv_run):
    _, out = adv_run
    rep = json.loads((out / "report.json").read_text())
    rnd = rep["adversarial"]["rounds"][0]
    assert rnd["added"] >= 1
    assert rnd["train_size"] == 2 + rnd["added"] == rep["train"]["start"]["n"]
    plants = files.read_npz(out / "round_1" / "plants.npz")
    coef = plants["plant.disturbance.coefficients"]
    assert coef.shape == (rnd["added"], 5)
    # the worst case found is the first plant added: its waveform and box values
    np.testing.assert_array_equal(coef[0], rnd["search"]["disturbance"]["coefficients"])
    for name, value in rnd["search"]["parameters"].items():
        assert plants[name][0] == value


def _inputs():
    raw = tomllib.loads(TOML)
    table = raw.pop("tuning")
    setup, options = config.from_dict(raw, base_spec=RunSpec.make(**tuning.config.SIMULATION))
    cfg = tuning.config.from_dict(table)
    return setup, options, dataclasses.replace(
        cfg, adversarial=dataclasses.replace(cfg.adversarial, rounds=1))


def _printed(cfg) -> str:
    """The [tuning] table of `cfg` by the library's writer (test_inputs reads back what
    `dscjax tune --print-config` prints)."""
    return config.dumps_toml({"tuning": tuning.config.to_table(cfg)})


def never(*a, **k):
    raise AssertionError("a finished phase ran again")


def test_resume_after_finished_rounds_redoes_nothing(adv_run, monkeypatch):
    _, out = adv_run
    before = {p: p.read_bytes() for p in (out / "adversarial.json",
                                          out / "round_1" / "history.csv")}
    monkeypatch.setattr(worst, "worst_case", never)
    monkeypatch.setattr(runner, "run", never)
    outcome = adversarial.run(*_inputs(), out, resume=True)
    for p, b in before.items():
        assert p.read_bytes() == b
    saved = json.loads((out / "adversarial.json").read_text())
    assert outcome.fresh == saved["fresh"]
    assert outcome.result.trace.iterations == saved["rounds"][0]["iterations"]


def test_killed_during_the_last_search_resumes_to_the_same_result(adv_run, tmp_path,
                                                                  monkeypatch):
    """A run killed while the tuned gains' fresh search ran (its state saved, the manifest
    not yet updated) reruns that search only, from its state, to the same worst case."""
    _, done = adv_run
    out = tmp_path / "out"
    shutil.copytree(done, out)
    meta = json.loads((out / "adversarial.json").read_text())
    expected = meta["fresh"].pop("tuned")
    (out / "adversarial.json").write_text(json.dumps(meta))
    calls = []
    search = worst.worst_case
    monkeypatch.setattr(worst, "worst_case", lambda *a, **k: calls.append(1) or search(*a, **k))
    monkeypatch.setattr(runner, "run", never)
    outcome = adversarial.run(*_inputs(), out, resume=True)
    assert len(calls) == 1
    assert outcome.fresh["tuned"] == expected


@pytest.mark.parametrize("value", ["-1", "1.5", "two"])
def test_bad_adversarial_rounds_give_one_line_and_exit_2(value, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:  # argparse's refusal of the option's value
        main(["tune", "--adversarial", value, "--out", str(tmp_path)])
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert "--adversarial" in err and ">= 0" in err and repr(value) in err


SEARCH_EVALS = 'tuning.adversarial.search_evals must be an integer >= 1, or "none"'
EFFORT_BOUNDS = "tuning.objective.effort_bounds must be one of 'nominal', 'per_plant'"


@pytest.mark.parametrize(("toml", "wanted"), [
    ("[tuning.adversarial]\nrounds = -2", "tuning.adversarial.rounds must be an integer >= 0 "
     "(got -2)"),
    ("[tuning.adversarial]\nrounds = 1\nsearch_evals = 0", f"{SEARCH_EVALS} (got 0)"),
    ("[tuning.adversarial]\nrounds = 1\nsearch_evals = 2.5", f"{SEARCH_EVALS} (got 2.5)"),
    ('[tuning.adversarial]\nrounds = 1\nsearch_evals = "many"',
     f"{SEARCH_EVALS} (got a string, 'many')"),
    ('[tuning.objective]\neffort_bounds = "everywhere"',
     f"{EFFORT_BOUNDS} (got a string, 'everywhere')"),
    ("[tuning.objective]\neffort_bounds = 1", f"{EFFORT_BOUNDS} (got 1)"),
])
def test_bad_config_values_name_the_field(toml, wanted, tmp_path, capsys):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(toml + "\n")
    assert main(["tune", "--config", str(cfg), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert err.endswith(wanted)


def test_search_evals_option_needs_adversarial_and_a_positive_count(tmp_path, capsys):
    assert main(["tune", "--search-evals", "8", "--out", str(tmp_path)]) == 2
    assert "--search-evals applies to adversarial tuning" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:
        main(["tune", "--adversarial", "1", "--search-evals", "-3", "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert stop.value.code == 2
    assert err.endswith("argument --search-evals: must be an integer >= 1, or \"none\" (got "
                        "'-3')")


def test_resume_refuses_another_search_evals(adv_run, run_with_config, capsys):
    """A run made without a cap does not resume with one: the cap changes which points each
    search sees, so it is part of the fingerprint once set (one line, exit 2, naming it)."""
    _, out = adv_run
    capsys.readouterr()
    code, _ = run_with_config(out.parent, TOML, "tune", "--adversarial", "1", "--search-evals",
                              "8", "--resume", "--quiet", "--no-plot")
    err = capsys.readouterr().err.strip()
    assert code == 2 and "Traceback" not in err
    # refused first: the one line, before the banner and any work
    assert len(err.splitlines()) == 1
    assert err.endswith("was made with other settings (adversarial.search_evals None (now 8)); "
                        "use the same settings, or --overwrite to start afresh")


def test_search_evals_ends_each_search_at_that_count(adv_run):
    """A count-capped search evaluates whole batches until it reaches the count, whatever
    time is left, and is the same search each time (same seed: same points, same worst)."""
    setup, options, cfg = _inputs()
    cfg = dataclasses.replace(cfg, adversarial=dataclasses.replace(
        cfg.adversarial, search_time=600.0, search_evals=6))
    runs = [adversarial.record(adversarial.search_worst(setup, options, cfg, seed=3))
            for _ in range(2)]
    assert runs[0]["evaluations"] == 8  # two batches of 4
    assert runs[0] == runs[1]
    assert "search_evals = \"none\"" in _printed(_inputs()[2])


# -- effort bounds per training plant (tuning.objective.effort_bounds = "per_plant") ----------


def _per_plant_problem(out):
    """The adversarial run's final training set (its random plants and the worst cases the
    round added, waveforms included) with effort_bounds = "per_plant"."""
    setup, options, cfg = _inputs()
    cfg = dataclasses.replace(cfg, objective=dataclasses.replace(
        cfg.objective, effort_bounds=tuning.optimize.PerPlant()))
    setup = adversarial.search_problem(setup, options, cfg).setup
    plants = files.read_npz(out / "round_1" / "plants.npz")
    return setup, runner.build_problem(setup, options, cfg, extra_plants=plants)


def _effort_figures(s):
    """(diverged, max|u|, TV(u) = sum |u_(k+1) - u_k|) of `s` over 0.4 s by `simulate`
    (every step saved) and numpy in the loop tuned (the controller sampled at 1 ms): the start
    bounds' independent reference."""
    traj = dscjax.simulate(s, 0.4, 1e-3, window_start=0.2, throw=False, refine=0,
                           sample_time=1e-3)
    u = np.asarray(traj.u, np.float64)
    return bool(traj.diverged), np.max(np.abs(u)), np.sum(np.abs(np.diff(u)))


def test_per_plant_bounds_are_the_start_gains_own_figures_on_each_plant(adv_run):
    """Each training plant's bounds equal the start gains simulated on that plant by
    `simulate`, with max|u| and TV(u) = sum |u_(k+1) - u_k| computed here by numpy over the
    step grid; the nominal bounds stay those of the nominal plant."""
    _, out = adv_run
    setup, problem = _per_plant_problem(out)
    sc, spec = problem.objective.scales, problem.cfg.objective
    ov = problem.objective.overrides
    n = problem.n_train
    assert n == 2 + len(files.read_npz(out / "round_1" / "plants.npz")["hysteresis.alpha"])
    assert sc.u_max_train.shape == sc.tv_max_train.shape == (n,)
    assert sc.u_max_train.dtype == sc.tv_max_train.dtype == np.float64

    def figures(s):
        _, u_max, tv = _effort_figures(s)
        return u_max, tv

    for i in range(n):
        u_max, tv = figures(dscjax.params.set_many(
            setup, {k: np.asarray(v)[i] for k, v in ov.items()}))
        assert sc.u_max_train[i] == pytest.approx(u_max, rel=1e-9)
        assert sc.tv_max_train[i] == pytest.approx(spec.tv_max_factor * tv, rel=1e-9)
    u_max, tv = figures(setup)
    assert sc.u_max == pytest.approx(u_max, rel=1e-9)
    assert sc.tv_max == pytest.approx(spec.tv_max_factor * tv, rel=1e-9)
    # the objective applies them: the start gains meet their own bounds on every plant
    _, aux = problem.objective.evaluate(problem.z0)
    assert bool(aux["feasible"])


def test_per_plant_bounds_keep_the_nominal_ones_where_the_start_diverges():
    """A training plant on which the start gains diverge (theta_1 = 1000: x_1' = 1000 x_1^2
    blows up from x_1(0) = 0.08 within about 1 / 80 s) keeps the nominal plant's bounds,
    exactly; the others get the start gains' own figures on them, computed here by
    `simulate` on each plant alone (max|u| and TV(u) = sum |u_(k+1) - u_k| by numpy)."""
    from dscjax.runspec import RunSpec

    setup = dscjax.paper_example()
    per_plant = tuning.ObjectiveSpec(effort_bounds=tuning.optimize.PerPlant())
    cfg = tuning.TuningConfig(params=("controller.k",), objective=per_plant,
                              robust=tuning.BatchSpec(batch=0),
                              heldout=tuning.BatchSpec(batch=0))
    theta = np.array([[0.2, 0.0], [1000.0, 0.0], [0.05, 0.0]])
    problem = runner.build_problem(setup, RunSpec.make(t_final=0.4, window_start=0.2,
                                                       sample_time=1e-3), cfg,
                                   extra_plants={"plant.theta": theta})
    sc = problem.objective.scales
    assert problem.n_train == 4  # the nominal plant, then the three added

    factor = cfg.objective.tv_max_factor

    def figures(s):
        diverged, u_max, tv = _effort_figures(s)
        return diverged, u_max, factor * tv

    plants = [setup] + [dscjax.params.set_many(setup, {"plant.theta": t}) for t in theta]
    runs = [figures(s) for s in plants]
    assert [d for d, _, _ in runs] == [False, False, True, False]
    assert sc.n_train_fallback == 1
    assert sc.u_max == pytest.approx(runs[0][1], rel=1e-9)
    assert sc.tv_max == pytest.approx(runs[0][2], rel=1e-9)
    assert sc.u_max_train[2] == sc.u_max and sc.tv_max_train[2] == sc.tv_max
    for i in (0, 1, 3):
        assert sc.u_max_train[i] == pytest.approx(runs[i][1], rel=1e-9)
        assert sc.tv_max_train[i] == pytest.approx(runs[i][2], rel=1e-9)
    # the plants that did not diverge have bounds of their own, not the nominal ones
    assert abs(sc.u_max_train[1] / sc.u_max - 1) > 1e-3
    assert abs(sc.tv_max_train[3] / sc.tv_max - 1) > 5e-4  # theta_1 0.05: TV(u) 0.1 % lower
    assert any("(1 on which the start gains diverge keep the nominal plant's)" in n
               for n in problem.notes)


def test_effort_bounds_are_part_of_the_fingerprint(adv_run):
    """nominal and per_plant bounds are two problems: a run does not resume with the
    other."""
    _, out = adv_run
    setup, options, cfg = _inputs()
    nominal = runner.build_problem(setup, options, cfg).describe()
    # what a resume is checked against is the built problem's description, built or not
    assert runner.describe(setup, options, cfg) == nominal
    assert nominal["objective"]["effort_bounds"] == "nominal"
    _, per = _per_plant_problem(out)
    assert per.describe()["objective"]["effort_bounds"] == "per_plant"
    assert 'effort_bounds = "nominal"' in _printed(cfg)
    again = tuning.config.from_dict(tomllib.loads(_printed(per.cfg))["tuning"])
    assert again.objective.effort_bounds.per_plant


def test_per_plant_report_checks_every_training_plant(tmp_path, run_with_config):
    """report.json and report.md state the bounds used and check them on each training
    plant: the start gains meet their own bounds on every plant. The nominal plant and the
    training batch are evaluated in one program (no other test here has its structure)."""
    toml = TOML.split("[tuning.adversarial]")[0]
    with counted() as seen:
        code, out = run_with_config(tmp_path, toml, "tune", "--effort-bounds", "per_plant",
                                    "--quiet", "--no-plot")
    assert code == 0
    assert seen["_per_plant"] == 1
    rep = json.loads((out / "report.json").read_text())
    assert rep["effort_bounds"] == "per_plant"
    assert len(rep["bounds_train"]["max_abs_u"]) == len(rep["bounds_train"]["tv_u"]) == 2
    for tag in ("start", "tuned"):
        rows = rep["train_constraints"][tag]
        # the effort bounds, then the check loops': the states by forward Euler (L-inf and
        # effort bounds), the input delayed a sample (L-inf and TV(u))
        euler, late = ", the states by forward Euler", ", the input delayed 1 sample"
        assert [r["name"] for r in rows] == ["max|u|", "TV(u)", "L-inf on [t0,T]" + euler,
                                             "max|u|" + euler, "TV(u)" + euler,
                                             "L-inf on [t0,T]" + late, "TV(u)" + late]
        assert all(r["bounds"] == "per_plant" and r["n"] == 2 for r in rows[:2])
    assert all(r["n_met"] == 2 for r in rep["train_constraints"]["start"][:2])
    tv = rep["train_constraints"]["start"][1]
    assert tv["worst_relative_margin"] == pytest.approx(1 - 1 / 1.5, rel=1e-6)
    md = (out / "report.md").read_text()
    assert "Constraints per training plant" in md and "on each training plant" in md


def test_search_programs_apply_each_candidate_the_plants_own_bounds(adv_run):
    """The batched programs of the search methods (every candidate x every training plant)
    lay the per-plant bounds out as the plants: their loss and feasibility are those of the
    objective evaluated at each candidate alone."""
    from jax.flatten_util import ravel_pytree

    from tuning import search

    _, out = adv_run
    _, problem = _per_plant_problem(out)
    flat0, unravel = ravel_pytree(problem.z0)
    # the start, and k_2 x 3: more effort than the start's on some plants
    pts = np.stack([np.asarray(flat0), np.asarray(flat0) + np.log([1.0, 3.0])])
    got = search.batch_fn(problem)(pts)
    losses = search.TuneProblem(problem).evaluate(pts).loss
    terms = []
    for i, p in enumerate(pts):
        loss, aux = problem.objective.evaluate(unravel(p))
        assert float(got["loss"][i]) == pytest.approx(float(loss), rel=1e-9)
        assert float(losses[i]) == pytest.approx(float(loss), rel=1e-9)
        assert bool(got["feasible"][i]) == bool(aux["feasible"])
        terms.append(float(aux["terms"]["u_bound"]))
    assert terms[1] > 0  # the bounds were in play


def test_rounds_padded_to_one_capacity_share_the_compiled_search(adv_run):
    """Issue 39 item 4: two rounds' training sets (the round's plants, then one more worst
    case) padded to one capacity run the search's batched and gradient programs compiled
    once; the padding weighs nothing: the loss is the worst real plant's, as the report's
    per-plant program gives them (the loop tuned alone: the check loops are not what is
    tested; the masked aggregates and gradient weights are test_tuning_config's)."""
    from tuning import report, search

    _, out = adv_run
    setup, options, cfg = _inputs()
    cfg = dataclasses.replace(cfg, objective=dataclasses.replace(
        cfg.objective, sampled_weight=0.0, delay_weight=0.0))
    setup = adversarial.search_problem(setup, options, cfg).setup
    first = files.read_npz(out / "round_1" / "plants.npz")
    more = {k: np.asarray(v)[:1] for k, v in first.items()}
    more["hysteresis.alpha"] = 1.1 * more["hysteresis.alpha"]
    second = runner.join_plants(setup, first, more)
    k = len(first["hysteresis.alpha"])
    capacity = 4 + k  # both rounds padded
    rounds = [runner.build_problem(setup, options, cfg, extra_plants=p, capacity=capacity)
              for p in (first, second)]
    assert [p.n_train for p in rounds] == [2 + k, 3 + k]
    assert [p.objective.batch_size for p in rounds] == [capacity] * 2
    assert rounds[1].mode == tuning.Plants()  # one plant weighed (max): plant by plant
    x0 = search.TuneProblem(rounds[0]).x0
    pts = np.stack([x0, x0 + 0.05])
    with counted() as seen:
        got = [(search.TuneProblem(p).evaluate(pts).loss, search.TuneProblem(p).value_and_grad(
            pts[1:])[1]) for p in rounds]
    assert seen["_batch"] == 1 and seen["_gradient"] == 1
    assert np.all(np.isfinite(got[1][1]))
    p = rounds[1]
    for i, x in enumerate(pts):
        per = report._per_plant(p.objective.program(), search.TuneProblem(p).point(x), None)
        loss = np.asarray(per["loss"])
        assert loss.shape == (capacity,)
        np.testing.assert_allclose(got[1][0][i], loss[:p.n_train].max(), rtol=1e-12)
