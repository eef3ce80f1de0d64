"""Min-max (adversarial) robust tuning: `dscjax tune --adversarial R`, [tuning.adversarial].

R rounds of: search the worst cases of the current gains over a box of plant parameters and
a bounded disturbance waveform (`dscjax.worst_case`, seed `seed + r`), add them to the
training set (their box values and waveform coefficients; the other plants get a zero
waveform), tune again from the current gains. Then a fresh search (seed `seed + FRESH_SEED`,
never trained on) for the start and the tuned gains gives the evidence:

    cfg = TuningConfig(robust=BatchSpec(batch=8), adversarial=AdversarialSpec(
        rounds=2, disturbance="fourier:16:0.5"))
    out = tuning.adversarial.run(setup, RunSpec.make(), cfg, out_dir="results/adv")
    out.result.best_setup, out.fresh["start"]["value"], out.fresh["tuned"]["value"]

Files in `out_dir`: adversarial.json (fingerprint, finished phases), round_<r>/ (the round's
tuning run, plants.npz, search/), fresh_start/, fresh_tuned_R<R>/. A finished phase is never
redone on resume; a finished run may be resumed with more rounds.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np

from dscjax import files, worst
from dscjax.markdown import table
from dscjax.progress import critical
from dscjax.runspec import RunSpec
from dscjax.validation import ConfigError
from dscjax.worst.report import summary as worst_summary
from tuning import checkpoint as ck
from tuning import runner
from tuning.config import TuningConfig
from tuning.runner import MANIFEST

FRESH_SEED = 10_000  # added to the seed of the fresh searches: never a round's seed


@dataclasses.dataclass
class Outcome:
    """The last round's tuning run (its problem holds the final training set), each round's
    record and the fresh searches' worst cases ("start", "tuned")."""

    result: runner.Result
    rounds: list[dict]
    fresh: dict[str, dict]


def search_problem(setup, options: RunSpec, cfg: TuningConfig) -> worst.Problem:
    """The worst-case problem of [tuning.adversarial] at the gains of `setup`."""
    spec = cfg.adversarial
    ranges = (spec.ranges if spec.ranges is not None
              else runner.model_default_ranges(cfg, setup).robust.ranges)
    tuned = [r.param.path for r in ranges if r.param.path in cfg.params]
    if tuned:
        raise ConfigError(f"tuning.adversarial.ranges: {tuned[0]} is tuned; it cannot be searched")
    return worst.make_problem(setup, list(ranges), spec.disturbance, metric=spec.metric,
                              spec=options, field="tuning.adversarial.ranges")


def search_worst(setup, options: RunSpec, cfg: TuningConfig, seed: int,
                 out_dir: Path | None = None) -> worst.Result:
    """The worst case of [tuning.adversarial] for the gains of `setup` (resumed from `out_dir`)."""
    spec = cfg.adversarial
    if out_dir is not None:
        files.mkdir(out_dir)
    return worst.worst_case(search_problem(setup, options, cfg), time_limit=spec.search_time,
                            seed=seed, out_dir=out_dir, resume=out_dir is not None,
                            starts=spec.starts, methods=(spec.method,), batch=spec.batch,
                            max_evals=spec.search_evals, coarsening=math.gcd(
                                worst.DEFAULT_COARSENING, int(options.sample_every))
                            if options.sampled else worst.DEFAULT_COARSENING)


def record(res: worst.Result) -> dict:
    """The worst case of a search as report.json gives it."""
    s = worst_summary(res)
    return {k: s[k] for k in ("metric", "value", "diverged", "t_diverged", "method",
                              "parameters", "disturbance", "nominal_value")} | {
        "evaluations": sum(tr.evaluations for tr in res.traces.values())}


def _worst_points(res: worst.Result, add: int) -> np.ndarray:
    """Up to `add` distinct worst points of a search, worst first: the re-checked worst case,
    then the best points each method kept (`Trace`'s top points, loss = -metric)."""
    cands = [c for tr in res.traces.values() for c in zip(tr.top_loss, tr.top_z, strict=True)]
    out: list[np.ndarray] = [np.asarray(res.z)]
    for _, z in sorted(cands, key=lambda c: c[0]):
        if len(out) < add and not any(np.array_equal(z, o) for o in out):
            out.append(np.asarray(z))
    return np.stack(out)


def run_fingerprint(searched: worst.Problem, problem: dict, cfg: TuningConfig) -> dict:
    """What adversarial.json stores to resume: `problem`, the tuning problem's description at
    the searched setup (whole, so that a refusal names the old and new values), and the
    [tuning.adversarial] settings (the rounds apart, the box as searched)."""
    adv = dataclasses.asdict(dataclasses.replace(cfg.adversarial, rounds=0,
                                                 ranges=[r.spec() for r in searched.ranges]))
    return {"problem": problem, "adversarial": adv}


def check_resume(out: str | Path, setup, options: RunSpec, cfg: TuningConfig) -> None:
    """`runner.check_resume` of an adversarial run (`run`'s arguments): nothing is run."""
    files.resume_file(out, MANIFEST)  # a missing run first, then the settings
    searched = search_problem(setup, options, cfg)
    fingerprint = run_fingerprint(searched, runner.describe(searched.setup, options, cfg), cfg)
    files.check_record(out, MANIFEST, fingerprint)


def _manifest(out: Path | None, fingerprint: dict, resume: bool, overwrite: bool) -> dict:
    meta = {"fingerprint": fingerprint, "rounds": [], "fresh": {}}
    if out is None:
        return meta
    if resume:
        return files.check_record(out, MANIFEST, fingerprint)
    runner.prepare_dir(out, False, overwrite)
    for old in [*out.glob("round_*"), *out.glob("fresh_*")]:
        shutil.rmtree(old)
    files.write_json(out / MANIFEST, meta)  # at once: a run killed in its first round resumes
    return meta


def run(setup, options: RunSpec, cfg: TuningConfig, out_dir: str | Path | None = None, *,
        resume: bool = False, overwrite: bool = False,
        progress: Callable[[dict], None] | None = None,
        say: Callable[[str], None] | None = None) -> Outcome:
    """Adversarial tuning with `cfg.adversarial.rounds` >= 1 rounds (the module doc), every
    phase saved in `out_dir` (None: nothing written or resumed); `cfg.optimizer`'s limits are
    each round's. `progress` gets each tuning row (with "round"), `say` a line per phase."""
    spec = cfg.adversarial
    cfg.validate()
    if spec.rounds < 1:
        raise ConfigError(f"tuning.adversarial.rounds must be >= 1 for adversarial tuning (got "
                          f"{spec.rounds})")
    say = say or (lambda text: None)
    out = None if out_dir is None else Path(out_dir)
    # the training plants need the waveform's coefficients as a leaf: a zero waveform
    searched = search_problem(setup, options, cfg)
    setup = searched.setup
    base = runner.build_problem(setup, options, cfg)
    meta = _manifest(out, run_fingerprint(searched, base.describe(), cfg), resume, overwrite)

    def save():
        if out is not None:
            files.write_json(out / MANIFEST, meta)

    def search(z, seed: int, where: str, label: str) -> worst.Result:
        cap = f" or {spec.search_evals} evaluations" if spec.search_evals else ""
        say(f"{label}: {spec.method} search for {spec.search_time:g} s{cap} (seed {seed})")
        return search_worst(base.setup_at(z), options, cfg, seed,
                            None if out is None else out / where)

    z, plants, result = base.z0, None, None
    for r in range(1, spec.rounds + 1):
        rdir = None if out is None else out / f"round_{r}"
        done = r <= len(meta["rounds"])
        if done:
            plants = files.read_npz(rdir / "plants.npz")
        else:
            res = search(z, spec.seed + r, f"round_{r}/search", f"round {r}/{spec.rounds}")
            zw = _worst_points(res, spec.add)
            new = {k: np.asarray(v) for k, v in res.problem.overrides(zw).items()}
            plants = new if plants is None else runner.join_plants(setup, plants, new)
            if rdir is not None:  # made by the round's search (its out_dir, rdir/search)
                files.write_npz(rdir / "plants.npz", plants)
            say(f"round {r}/{spec.rounds}: worst {spec.metric} {res.value:.6g} for the current "
                f"gains; {len(zw)} worst cases join the training set")
        # every round's plants padded to the last round's count: one compiled program
        problem = runner.build_problem(setup, options, cfg, extra_plants=plants,
                                       capacity=max(cfg.robust.batch, 1) + spec.rounds * spec.add)
        if done:
            result = runner.finished(problem, rdir)
        else:
            say(f"round {r}/{spec.rounds}: tuning on {problem.n_train} plants")
            row_cb = None if progress is None else (lambda row, r=r: progress(row | {"round": r}))
            result = runner.run(problem, rdir, z_init=z, progress=row_cb,
                                resume=rdir is not None and (rdir / ck.RECORD).exists())
            with critical():  # the round's record and its file (dscjax.progress)
                meta["rounds"].append({
                    "round": r, "search": record(res), "added": len(zw),
                    "train_size": problem.n_train, "iterations": result.trace.iterations,
                    "stop_reason": result.stop_reason, "best_loss": result.trace.best_loss})
                save()
        z = jax.device_get(result.best_z)
    fresh = meta.setdefault("fresh", {})
    seed = spec.seed + FRESH_SEED
    for tag, zz, where, rounds in (("start", base.z0, "fresh_start", None),
                                   ("tuned", z, f"fresh_tuned_R{spec.rounds}", spec.rounds)):
        if tag in fresh and fresh[tag]["rounds"] == rounds:
            continue  # done (the start gains' search does not depend on the rounds)
        found = record(search(zz, seed, where, f"fresh search, {tag} gains"))
        with critical():
            fresh[tag] = found | {"seed": seed, "rounds": rounds}
            save()
    if out is not None:
        runner.write_best(out, result.problem, result.trace)
    return Outcome(result=result, rounds=meta["rounds"], fresh=fresh)


def markdown(summary: dict) -> str:
    """The report.md section of an adversarial run."""
    lines = ["", "## Adversarial rounds (min-max)", "", *table(
        ("round", "worst case of the current gains", "method", "added", "training plants",
         "iterations", "stopped"),
        [(r["round"], worst_text(r["search"]), r["search"]["method"], r["added"],
          r["train_size"], r["iterations"], r["stop_reason"]) for r in summary["rounds"]])]
    a, b = summary["fresh"]["start"], summary["fresh"]["tuned"]
    lines += ["", "## Fresh worst-case search", "", fresh_sentence(summary), "",
              *table(("", "start gains", "tuned gains"), [
                  (f"nominal {a['metric']}", f"{a['nominal_value']:.6g}",
                   f"{b['nominal_value']:.6g}"),
                  ("evaluations", a["evaluations"], b["evaluations"])]), "",
              "Worst values re-checked by `simulate` on the worst setup (docs/worst-case.md); "
              "the worst parameters and waveforms: report.json `adversarial.fresh`.", ""]
    return "\n".join(lines)


def fresh_sentence(summary: dict) -> str:
    """The fresh searches' worst cases and the training set's growth (report.json's
    "adversarial"): a line of report.md and the console's."""
    a, b = summary["fresh"]["start"], summary["fresh"]["tuned"]
    return (f"Fresh worst-case search (seed {a['seed']}, never trained on): worst {a['metric']} "
            f"{worst_text(a)} (start gains) -> {worst_text(b)} (tuned gains); training set "
            f"{' -> '.join(str(n) for n in summary['train_sizes'])} plants.")


def worst_text(s: dict) -> str:
    """A search's worst value, or when its worst case diverges."""
    if s["diverged"]:
        return f"diverges at t = {s['t_diverged']:.4g} s"
    return f"{s['value']:.6g}"


def add_to_report(out: str | Path, summary: dict, outcome: Outcome) -> dict:
    """Add the adversarial section to report.json and report.md (`tuning.report.write`'s)."""
    out = Path(out)
    summary["adversarial"] = {"rounds": outcome.rounds, "fresh": outcome.fresh,
                              "train_sizes": [r["train_size"] for r in outcome.rounds]}
    files.write_json(out / "report.json", summary)
    md = (out / "report.md").read_text()
    files.write_text(out / "report.md", md.rstrip("\n") + "\n" + markdown(summary["adversarial"]))
    return summary
