"""An identification from settings to files: `IdentifySettings` (the [identify] table, each
setting declared once), `identify` (fit, statistics, validation) and `write` (identified.toml,
report.md, report.json, fit.png, residuals.png).

identified.toml is a whole config: the model's with the identified numbers, and their 95 %
intervals as [tuning.robust.ranges], the box `dscjax tune --batch B` then tunes for.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from dscjax import config, files
from dscjax.identify import fit as fitting
from dscjax.identify.data import Record, read
from dscjax.identify.experiment import HOLDS, Experiment, simulate
from dscjax.markdown import table, verdict
from dscjax.rules import AtLeast, Choice, Maybe, Number, Strings, Text
from dscjax.sensitivity import columns
from dscjax.settings import setting
from dscjax.validation import ConfigError, by_rule

FIGURES = ("fit.png", "residuals.png")
VALIDATION_SHARE = 0.25  # without --validate, the record's last quarter validates


@dataclasses.dataclass(frozen=True)
class IdentifySettings:
    """[identify]: what `dscjax identify` fits and how."""

    free: tuple[str, ...] = setting((), "the numbers fitted: config paths (a vector whole, or "
                                    "one element), e.g. plant.g,hysteresis.alpha", Strings(),
                                    flag="--free")
    segments: int = setting(1, "multiple shooting: segments of the record, each plant segment "
                            "from a start state of its own (fitted)", AtLeast(1),
                            flag="--segments")
    starts: int = setting(1, "fits from the config's numbers and from starts scattered around "
                          "them (x e^+-0.5); the best is kept", AtLeast(1), flag="--starts")
    hold: str = setting("zoh", "u between two samples: zoh (held, as a digital controller "
                        "holds it) or linear", Choice(HOLDS), flag="--hold")
    validate: str | None = setting(None, "a second record to validate on; none: the last "
                                   "quarter of the record", Maybe(Text()), flag="--validate")
    max_steps: int = setting(200, "Levenberg-Marquardt steps at most", AtLeast(1),
                             flag="--max-steps")
    seed: int = setting(0, "seed of the scattered starts", AtLeast(0), flag="--seed")
    noise: float | None = setting(None, "the measurement noise std of every measured column; "
                                  "none: estimated from each column's second differences",
                                  Maybe(Number(gt=0)), flag="--noise-std")


@dataclasses.dataclass(frozen=True)
class Identified:
    """What `identify` found: the fit's problem and solution, the estimates, the figures of
    the fit and of the validation, and how long it took."""

    problem: fitting.Problem
    fit: fitting.Fit
    estimates: list
    corr: np.ndarray
    singular_values: np.ndarray
    s2: float
    figures: dict
    validation: dict
    validation_source: str
    val_problem: fitting.Problem
    val_fit: fitting.Fit
    start_costs: list
    seconds: float


def check_free(setup, free, plant: bool = True) -> None:
    """Refuse an empty `free`, each path the setup lacks and each number that does not act on
    the experiment (ConfigError): the plant's and the actuator's numbers act on a plant
    record, the actuator's alone on an actuator record (u and w); the controller and the
    reference never act (the measured u drives the experiment)."""
    if not free:
        raise ConfigError("--free: give the numbers to fit, e.g. --free "
                          "plant.g,hysteresis.alpha (or [identify] free in the config)")
    columns(setup, free, "--free")
    acting = ("plant.", "hysteresis.") if plant else ("hysteresis.",)
    idle = [p for p in free if not p.startswith(acting)]
    if idle:
        raise ConfigError(f"--free must name {' or '.join(a + '*' for a in acting)} numbers, "
                          f"which act on {'a plant' if plant else 'an actuator (u, w)'} record "
                          f"(got {', '.join(idle)})")


def check_validation(val: Record, record: Record) -> Record:
    """`val`, refused in one line unless it measures the columns of the fitted `record`: the
    report sets each column's fit beside its validation fit, a column's noise std is the
    fit's, and the fit's columns chose the experiment (the plant, or the actuator alone)."""
    if list(val.y) != list(record.y):
        raise ConfigError(f"--validate: {val.source} measures {', '.join(val.y)}; it must "
                          f"measure the columns of --data {record.source}: "
                          f"{', '.join(record.y)}")
    return val


def validation_record(path: str, record: Record, order: int) -> Record:
    """The record of --validate (`read`), checked before any fit (`check_validation`)."""
    return check_validation(read(path, order, "--validate"), record)


def identify(setup, spec, record: Record, s: IdentifySettings, validation: Record | None
             = None) -> Identified:
    """Fit `s.free` of `setup` to `record` (the plant experiment where the record measures a
    plant state, the actuator alone where it measures w only), then validate on `validation`
    (default: the record's last quarter, which the fit then leaves out)."""
    plant = record.plant
    fitted = len(record)  # the samples the fit reads
    if validation is None:
        fitted = int(round(fitted * (1 - VALIDATION_SHARE)))
        fit_index, val = np.arange(fitted), record.part(fitted - 1)
        where = (f"the last {100 * VALIDATION_SHARE:g} % of the record (t >= "
                 f"{record.t[fitted - 1]:g} s)")
    else:
        fit_index, val, where = None, check_validation(validation, record), validation.source
    check_free(setup, s.free, plant)
    by_rule(AtLeast(1), s.segments, "--segments")
    if s.segments > fitted // 10:
        raise ConfigError(f"--segments must be at most {fitted // 10} for {fitted} samples (10 "
                          f"a segment; got {s.segments})")
    sigma = None if s.noise is None else {c: s.noise for c in record.y}
    t0 = time.perf_counter()
    problem = fitting.Problem.make(setup, record, s.free, plant=plant, dt=float(spec.dt),
                                   segments=s.segments, hold=s.hold, sigma=sigma,
                                   fit_index=fit_index)
    fit, costs = fitting.solve_starts(problem, s.starts, s.seed, max_steps=s.max_steps)
    if not math.isfinite(fit.cost):
        raise ConfigError("the fit diverged from every start (the model left the finite "
                          "numbers): give starts closer to the data, more --segments, or more "
                          "--starts")
    h0 = None
    if validation is None:  # the actuator goes on into the tail from where the fit left it
        h0 = simulate(problem.setup_at(jnp.asarray(fit.theta["z"])),
                      Experiment.make(record.t[:fitted], record.u[:fitted], plant=False,
                                      dt=float(spec.dt), hold=s.hold), final=True)
    val_problem, val_fit = fitting.validation_fit(problem, fit, val, h0)
    return Identified(problem, fit, *fitting.estimates(problem, fit),
                      fitting.fit_figures(problem, fit), fitting.fit_figures(val_problem, val_fit),
                      where, val_problem, val_fit, costs, time.perf_counter() - t0)


def write(out: Path, res: Identified, spec, source: dict, plot: bool = True) -> list[str]:
    """identified.toml, report.json, report.md (and the figures): the names written."""
    table = config.to_dict(res.val_problem.setup, spec)  # the identified setup, validated
    # the robust tuning box: the 95 % interval of each identifiable number (the report names
    # the others)
    box = {e.name: [e.low, e.high] for e in res.estimates if e.identifiable}
    if box:
        table["tuning"] = {"robust": {"ranges": box}}
    header = (f"dscjax identify: {', '.join(e.name for e in res.estimates)} of "
              f"{source['model']} fitted to {source['data']};\n[tuning.robust.ranges]: their "
              f"95 % intervals, the box `dscjax tune --config identified.toml --batch B` tunes for")
    files.write_text(out / "identified.toml", config.dumps_toml(table, header=header))
    summary = summary_of(res, source, box)
    files.write_json(out / "report.json", summary)
    files.write_text(out / "report.md", markdown(summary))
    if plot:
        from dscjax.identify import plots

        plots.write(out, res)
    return ["identified.toml", "report.json", "report.md", *(FIGURES if plot else ())]


def summary_of(res: Identified, source: dict, box: dict) -> dict:
    p, fit = res.problem, res.fit
    x = np.asarray(fit.theta["x"])
    states = ([{"t": float(p.record.t[k]), "x": x[i].tolist()}
               for i, k in enumerate(p.exp.starts)] if p.exp.plant else None)
    return {
        "data": source, "samples": len(p.record), "fitted_samples": int(len(p.fit_index)),
        "experiment": "plant" if p.exp.plant else "actuator",
        "columns": list(p.record.y), "hold": p.exp.hold,
        "noise_std": {c: float(v) for c, v in p.sigma.items()},
        "segments": p.exp.segments, "substeps": p.exp.substeps,
        "solver": {"method": "Levenberg-Marquardt, exact Jacobians by forward mode",
                   "steps": fit.steps, "status": fit.status, "cost": fit.cost,
                   "starts": res.start_costs, "best_start": fit.start,
                   "seconds": res.seconds},
        "fit": res.figures, "validation": {"on": res.validation_source,
                                           "figures": res.validation},
        "parameters": [dataclasses.asdict(e) for e in res.estimates],
        "not_identifiable": [e.name for e in res.estimates if not e.identifiable],
        "correlation": np.round(res.corr, 6).tolist(),
        "singular_values": res.singular_values.tolist(),
        "residual_variance_factor": res.s2, "segment_start_states": states,
        "robust_box": box,
    }


def markdown(s: dict) -> str:
    fit, val = s["fit"], s["validation"]["figures"]
    cols = [c for c in fit if c != "all"]
    lines = [
        "# Identification", "",
        f"{s['data']['data']}: {s['samples']} samples ({s['fitted_samples']} fitted), measured "
        f"{', '.join(s['columns'])}; the {s['experiment']} experiment, u "
        f"{'held' if s['hold'] == 'zoh' else 'linear'} between samples, {s['segments']} "
        f"segment(s). Model: {s['data']['model']}.", "",
        f"Levenberg-Marquardt on exact Jacobians: {s['solver']['steps']} steps "
        f"({s['solver']['status']}), {len(s['solver']['starts'])} start(s), "
        f"{s['solver']['seconds']:.1f} s.", "",
        "## Fit", "",
        *table(("output", "fit to estimation data (NRMSE %)", "MSE", "validation fit (NRMSE %)"),
               [(c, f"{fit[c]['nrmse_fit_percent']:.2f}", f"{fit[c]['mse']:.4g}",
                 f"{val[c]['nrmse_fit_percent']:.2f}") for c in cols])]
    lines += ["", f"FPE {fit['all']['fpe']:.4g}; validation on {s['validation']['on']} (the "
              "identified numbers fixed, the initial state fitted).", "",
              "## Parameters", "",
              *table(("parameter", "value", "standard error", "95 % interval", "identified"),
                     [(f"`{e['name']}`", f"{e['value']:.6g}", f"{e['se']:.3g}",
                       f"[{e['low']:.6g}, {e['high']:.6g}]",
                       verdict(None if e["identifiable"] else e["why"]))
                      for e in s["parameters"]])]
    if s["not_identifiable"]:
        lines += ["", f"**Not identifiable from this record**: {', '.join(s['not_identifiable'])}"
                  " (other values fit as well): leave them out of --free, or excite them."]
    names = [e["name"] for e in s["parameters"]]
    lines += ["", "Correlation of the estimates:", "",
              *table(("", *(f"`{n}`" for n in names)),
                     [(f"`{n}`", *(f"{v:.3f}" for v in row))
                      for n, row in zip(names, s["correlation"], strict=True)])]
    sv = s["singular_values"]
    lines += ["", f"Singular values of the weighted Jacobian: {sv[0]:.4g} ... {sv[-1]:.4g} "
              f"(ratio {sv[-1] / sv[0] if sv[0] > 0 else math.nan:.3g}); noise std "
              + ", ".join(f"{c} {v:.3g}" for c, v in s["noise_std"].items())
              + f"; residual variance factor {s['residual_variance_factor']:.3g}.", ""]
    if s["robust_box"]:
        lines += ["identified.toml: the identified config, with the 95 % intervals above as "
                  "[tuning.robust.ranges]; `dscjax tune --config DIR/identified.toml --batch B` "
                  "tunes for them.", ""]
    return "\n".join(lines)


__all__ = ["FIGURES", "IdentifySettings", "Identified", "identify", "markdown", "summary_of",
           "check_validation", "validation_record", "write"]
