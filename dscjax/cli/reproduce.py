"""`dscjax reproduce`: the paper's Section 4 in one command. Simulates its example (the DSC,
both readings without compensation, adaptive backstepping); writes Figs. 1-6, the adaptive
estimates, summary.json and summary.md, each claim of the paper checked. `--complexity` also
measures the size and cost of both control laws against the order n (it takes minutes)."""

from __future__ import annotations

from pathlib import Path

from dscjax import files, ts_sweep
from dscjax.cli import common, out
from dscjax.cli.out import Outputs, add_out_arg, add_overwrite_arg, start
from dscjax.reproduce import ROWS, claim_lines, reproduce, sampling, setups, written
from dscjax.reproduce.figures import FIGURES
from dscjax.validation import ConfigError, Work, check_work, validate_run, whole_steps

OUTPUTS = Outputs(("summary.json", "summary.md", "complexity.json", ROWS,
                   *(f"{stem}.{fmt}" for stem in FIGURES.values() for fmt in ("png", "pdf"))),
                  folders=("theory",))


def parse_orders(text: str, option: str) -> list[int]:
    """"2-8" or "2,3,5" -> list of orders >= 2; errors name `option`, the option that gave it."""
    try:
        if "-" in text.strip().lstrip("-"):
            lo, hi = (int(p) for p in text.split("-", 1))
            orders = list(range(lo, hi + 1))
        else:
            lo = hi = None
            orders = [int(p) for p in text.split(",") if p.strip()]
    except ValueError:
        raise ConfigError(f"{option} must look like '2-8' or '2,3,4' (got {text!r})") from None
    if lo is not None and lo > hi:
        raise ConfigError(f"{option}: a range N-M needs N <= M (got {text!r}; did you mean "
                          f"{hi}-{lo}?)")
    if not orders:
        raise ConfigError(f"{option} must name at least one order n >= 2 (got {text!r})")
    if min(orders) < 2:
        raise ConfigError(f"{option} must be orders n >= 2 (got {text!r}, which includes "
                          f"n = {min(orders)})")
    return orders


HELP = "reproduce the paper's simulation study (Figs. 1-6, claims)"


def add_options(p):
    from dscjax import reproduce as r

    orders = f"{min(r.COMPLEXITY_ORDERS)}-{max(r.COMPLEXITY_ORDERS)}"
    add_out_arg(p, "results/paper", later=True)
    p.add_argument("--format", choices=("png", "pdf"), default="png", dest="fmt",
                   help="figure format (default: png)")
    p.add_argument("--dpi", type=common.count(10), default=r.DPI,
                   help="resolution of PNG figures (default %(default)s)")
    common.add_run_args(p, ("t_final", "dt", "device"), defaults={"t_final": r.T_FINAL, "dt": r.DT})
    p.set_defaults(t_final=r.T_FINAL, dt=r.DT)
    p.add_argument("--complexity", action="store_true",
                   help="also measure the explosion of complexity (control law against order n)")
    p.add_argument("--orders", default=orders, metavar="N-M",
                   help="orders for --complexity, e.g. 2-8 or 2,4,6 (default %(default)s)")
    p.add_argument("--repeats", type=common.count(1), default=r.COMPLEXITY_REPEATS, metavar="R",
                   help="builds per law for --complexity, timed by median (default %(default)s)")
    add_overwrite_arg(p, resume="with --complexity: keep the measurements an interrupted run "
                      f"saved in DIR/{ROWS} (same --repeats), measure the rest",
                      plot="write no figures: summary.json, summary.md and the claims only")
    p.add_argument("--theory", action="store_true",
                   help="also check Theorem 1 on the DSC run (DIR/theory/) and run the alpha_0 "
                   "study (gains (55), tau (60), init (67)-(68)); minutes for n >= 3")
    p.add_argument("--theory-orders", default="2", metavar="N,M",
                   help="orders of the alpha_0 study for --theory, e.g. 2,3,4 (default 2)")
    p.add_argument("--alpha0", metavar="A,B,...", help="alpha_0 values of the study (default "
                   "by order: docs/theory.md)")
    p.add_argument("--mu", type=common.positive_float, metavar="MU",
                   help="mu of (59)-(60) for the study (default by order: docs/theory.md)")


def run(args) -> int:
    orders = parse_orders(args.orders, "--orders")
    theory_orders = parse_orders(args.theory_orders, "--theory-orders")
    alpha0 = common.positive_numbers(args.alpha0, "--alpha0")
    steps = whole_steps(args.t_final, args.dt, "--t-final", "--dt")
    validate_run(setups()["dsc"], args.t_final, args.dt, None)
    runs = len(setups())  # each saved at every step and kept for the figures
    point = common.loop_sizes(setups()["dsc"])
    extra = ts_sweep.total_steps(args.t_final, args.dt)
    check_work(Work(steps=runs * steps + extra,
                    member_steps=runs * steps + len(sampling.GAINS) * extra,
                    memory=runs * (steps + 1) * point[1] * point[2],
                    memory_what=f"the {runs} runs saved at every step"),
               what=common.horizon_text(args.t_final, args.dt, steps), fix=common.SHORTER)
    if args.resume and not args.complexity:
        raise ConfigError("--resume continues an interrupted --complexity study (the "
                          "closed-loop runs take seconds and are not kept); add --complexity")
    if args.resume:
        files.resume_file(args.out, ROWS)
    # one trajectory at a time
    start(args, OUTPUTS, "", args.device or "auto", resumable=args.complexity)
    summary = reproduce(args.out, fmt=None if args.no_plot else args.fmt, t_final=args.t_final,
                        dt=args.dt, dpi=args.dpi, complexity=args.complexity,
                        complexity_orders=orders, complexity_repeats=args.repeats,
                        resume=args.resume, theory=args.theory, theory_orders=theory_orders,
                        theory_alpha0=alpha0, theory_mu=args.mu)
    # the results on stdout (progress went to stderr); the sampling study's as in summary.md
    print("\n".join([*claim_lines(summary),
                     "sampled controller: " + "; ".join(sampling.findings(summary["sampling"])),
                     f"wrote {written(summary)} to {args.out}/"]))
    return 0


def resumable(args) -> bool:
    """Does --out hold what `--resume` continues (the --complexity study's measurements)?"""
    return bool(args.complexity) and (Path(args.out) / ROWS).exists()


def interrupt_hint(args) -> str:
    if resumable(args):
        return out.resume_text(args, "the finished control-law measurements are kept in "
                               f"{Path(args.out) / ROWS}")
    return out.kept_text(args, OUTPUTS)
