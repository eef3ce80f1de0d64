"""Sweeps (issue 5): equal to single runs, independent of chunk size and device count,
resumable to the same file, and clear about bad settings.

Short horizons (0.5 s) and a few dozen samples; the compiled block program is shared between
the tests through identical shapes and settings (float64, chunk 8, alpha/lam/psi).
"""

import dataclasses
import json
import os
import re
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from commands import exit_code
from reference_metrics import chattering_numpy

import dscjax
from dscjax import sweep
from dscjax.cli.main import main as cli
from dscjax.params import Grid, LatinHypercube, Param, Range
from dscjax.reproduce.sampling import TUNED
from dscjax.sweep import SweepSettings, run_sweep
from dscjax.sweep import device as sweep_device

T, DT = 0.5, 1e-3
BASE = SweepSettings(samples=24, chunk=8, dtype="float64")  # alpha, lam, psi +-30 %


@pytest.fixture(scope="module")
def base_result(paper_setup):
    return run_sweep(paper_setup, BASE, t_final=T, dt=DT)


def _same(a, b):
    assert set(a) == set(b)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_sweep_equals_single_simulations(paper_setup):
    ranges = (Range(Param("hysteresis.alpha"), rel=0.3), Range(Param("plant.g", 1), 0.8, 1.2),
              Range(Param("plant.theta", 0), 0.0, 0.2), Range(Param("plant.x0", 0), 0.05, 0.1),
              Range(Param("plant.dbar_amp"), 0.0, 0.5))
    settings = SweepSettings(samples=12, chunk=8, dtype="float64", method=LatinHypercube(),
                             ranges=ranges)
    res = run_sweep(paper_setup, settings, t_final=T, dt=DT)
    rows = [0, 5, 11]
    trajs = sweep.simulate_rows(paper_setup, res, rows, save_every=1)
    for i, tr in zip(rows, trajs, strict=True):
        for m in sweep.METRICS:
            np.testing.assert_allclose(res.columns[m][i], float(tr.metrics[m]), rtol=1e-9,
                                       atol=1e-15, err_msg=m)
        assert bool(res.columns["diverged"][i]) == bool(tr.diverged)
    # an independent single run (not through simulate_rows) for one sample
    i = 5
    g = np.array([1.0, res.columns["plant.g[1]"][i]])
    theta = np.array([res.columns["plant.theta[0]"][i], 0.0])
    x0 = np.array([res.columns["plant.x0[0]"][i], 0.1])
    s = dscjax.params.set_many(paper_setup, {
        "hysteresis.alpha": res.columns["hysteresis.alpha"][i], "plant.g": g,
        "plant.theta": theta, "plant.x0": x0, "plant.dbar_amp": res.columns["plant.dbar_amp"][i]})
    tr = dscjax.simulate(s, T, DT, throw=False)
    np.testing.assert_allclose(res.columns["linf_error_window"][i],
                               float(tr.metrics["linf_error_window"]), rtol=1e-9)
    # the table is a product of the ranges: every column stays inside its range
    for r in ranges:
        q = r.resolve(paper_setup)
        v = res.columns[r.name]
        assert v.min() >= q.low and v.max() <= q.high


def test_chunk_size_does_not_change_results(paper_setup, base_result):
    for chunk in (16,):  # 16: two blocks, the second padded
        other = run_sweep(paper_setup, SweepSettings(samples=24, chunk=chunk, dtype="float64"),
                          t_final=T, dt=DT)
        _same(base_result.columns, other.columns)


# the tile of the small sweeps here (tile_rows(cpu, n <= 64)): one compiled program for them all
W = 64
TILE_CHUNKS = (W, 2 * W, 3 * W + 5)  # one tile a block, two, and a block of 4 tiles, 1 padded


def test_tile_width():
    assert [sweep_device.tile_rows("cpu", n) for n in (1, 24, 64, 65, 257, 10**6)] == [
        64, 64, 64, 128, 512, sweep_device.CPU_TILE_ROWS]
    assert sweep_device.tile_rows("gpu", 10**7) == sweep_device.ACCELERATOR_TILE_ROWS


def _over_chunks(setup, settings, t_final):
    return [run_sweep(setup, dataclasses.replace(settings, chunk=c), t_final=t_final,
                      dt=DT, tile=W).columns for c in TILE_CHUNKS]


def test_float64_results_and_refinements_are_bitwise_independent_of_chunk(paper_setup):
    # alpha up to 10 with lam down to 0.15: some rows diverge with RK4 and are refined; which
    # rows share a refinement batch (and a tile) depends on the chunk, their bits must not
    ranges = (Range(Param("hysteresis.alpha"), 1.0, 10.0),
              Range(Param("hysteresis.lam"), 0.15, 3.0),
              Range(Param("hysteresis.psi"), 0.08, 0.13))
    n = 3 * W + 40
    runs = _over_chunks(paper_setup, SweepSettings(samples=n, dtype="float64", ranges=ranges),
                        T)
    refined = runs[0]["refinements"] > 0
    assert refined.sum() >= 2 and len(set(np.flatnonzero(refined) // W)) >= 2  # several blocks
    assert runs[0]["sample"].tolist() == list(range(n))
    for other in runs[1:]:
        _same(runs[0], other)


def test_float32_results_are_bitwise_independent_of_chunk(paper_setup):
    """tune's gains chatter in float32: over 2 s, programs compiled for the widths 64 and 197
    (one per chunk, as before tiles) give TV(u) and L2(u) far apart on a few of these rows;
    every block now runs the same tile program."""
    tuned = dscjax.config.from_dict({"controller": TUNED}, base=paper_setup)[0]
    runs = _over_chunks(tuned, SweepSettings(samples=3 * W + 40, dtype="float32"), 2.0)
    assert np.ptp(runs[0]["tv_u"]) > 0
    for other in runs[1:]:
        _same(runs[0], other)


def test_tiles_pad_with_a_valid_row():
    rows = np.arange(10.0).reshape(5, 2)
    t = dscjax.xla.tiles(rows, 2)
    assert len(t) == 3 and all(x.shape == (2, 2) for x in t)
    np.testing.assert_array_equal(np.concatenate(t)[:5], rows)
    np.testing.assert_array_equal(t[2], [[8.0, 9.0], [8.0, 9.0]])


def test_float32_metrics_are_rechecked_in_float64(paper_setup):
    """tune's gains (high k, small tau) make the float32 loop chatter: within 2 s (the
    horizon of test_float32_results_are_bitwise_independent_of_chunk, whose programs it
    shares) its TV(u) and L2 metrics differ from float64 by far more than round-off, and no
    float64 sum of the float32 run would repair that. The re-check measures the difference on
    a few rows (against an independent float64 batch here) and flags exactly the metrics
    beyond its tolerance."""
    tuned = dscjax.config.from_dict({"controller": TUNED}, base=paper_setup)[0]
    t = 2.0
    s32 = run_sweep(tuned, SweepSettings(samples=8, chunk=8, dtype="float32"), t_final=t, dt=DT)
    rows = sweep.check_rows(s32, [0, 1], least=4)
    assert len(rows) == 4 and {0, 1} <= set(rows.tolist())
    check = sweep.float64_check(tuned, s32, rows)
    # the reference: one float64 batch of the very parameter values the float32 sweep ran
    s64 = dscjax.simulate_batch(tuned, {p: s32.columns[p][rows] for p in s32.param_names},
                                t, DT)
    tol = sweep.FLOAT32_RTOL
    for m in sweep.METRICS:
        a, ref = s32.columns[m][rows], np.asarray(s64.metrics[m])
        diff = float(np.max(np.abs(a - ref) / np.abs(ref)))
        assert abs(check["max_rel_diff"][m] - diff) <= 0.05 * diff + 1e-6, m
        if diff > 2 * tol:
            assert m in check["untrusted"], m
        elif diff < tol / 2:
            assert m not in check["untrusted"], m
    assert {"tv_u", "l2_u"} <= set(check["untrusted"])
    assert "linf_error" not in check["untrusted"]  # pinned by the initial error, |x1(0)|
    f64 = dataclasses.replace(s32, info=s32.info | {"dtype": "float64"})
    assert sweep.float64_check(tuned, f64, rows) is None  # nothing to re-check in float64
    # summary.md says which metrics float32 cannot be trusted with
    summary = sweep.summarize(s32) | {"float32_check": check, "run": s32.info}
    md = sweep.markdown(summary)
    assert f"**Not trusted in float32: {', '.join(check['untrusted'])}**" in md
    assert f"| tv_u | {check['max_rel_diff']['tv_u']:.4g} | " in md
    assert "| linf_error | " in md.split("## float32 trust")[1]


def test_resume_after_interrupt_gives_the_same_file(paper_setup, tmp_path):
    full = run_sweep(paper_setup, BASE, t_final=T, dt=DT, out_dir=tmp_path / "a")

    def stop(p):  # called first after the first round
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_sweep(paper_setup, BASE, t_final=T, dt=DT, out_dir=tmp_path / "b", progress=stop)
    assert len(list((tmp_path / "b" / "chunks").glob("*.npz"))) == 1
    assert not (tmp_path / "b" / "results.npz").exists()
    # a half-written chunk (e.g. killed while writing) is not trusted
    (tmp_path / "b" / "chunks" / "chunk_000001.npz").write_bytes(b"PK\x03\x04 truncated")
    res = run_sweep(paper_setup, BASE, t_final=T, dt=DT, out_dir=tmp_path / "b", resume=True)
    assert res.info["samples_resumed"] == 8 and res.info["samples_run"] == 16
    a = (tmp_path / "a" / "results.npz").read_bytes()
    assert a == (tmp_path / "b" / "results.npz").read_bytes()
    _same(full.columns, res.columns)
    # resuming a finished sweep runs nothing and rewrites the same file
    again = run_sweep(paper_setup, BASE, t_final=T, dt=DT, out_dir=tmp_path / "b", resume=True)
    assert again.info["samples_run"] == 0
    assert a == (tmp_path / "b" / "results.npz").read_bytes()


def test_resume_refuses_other_settings_and_existing_dirs(paper_setup, tmp_path):
    out = tmp_path / "s"
    run_sweep(paper_setup, BASE, t_final=T, dt=DT, out_dir=out)
    with pytest.raises(dscjax.ConfigError, match="other settings.*seed"):
        run_sweep(paper_setup, SweepSettings(samples=24, chunk=8, dtype="float64", seed=1),
                  t_final=T, dt=DT, out_dir=out, resume=True)
    with pytest.raises(dscjax.ConfigError, match="--resume.*--overwrite"):
        run_sweep(paper_setup, BASE, t_final=T, dt=DT, out_dir=out)


def test_one_and_four_devices_give_identical_float64_metrics(base_result, four_devices):
    import four_devices as script  # the same sweep, run on 4 forced host devices

    assert script.SWEEP == dict(samples=BASE.samples, chunk=BASE.chunk, dtype=BASE.dtype,
                                t_final=T, dt=DT)
    result = json.loads((four_devices / "results.json").read_text())["sweep"]
    assert result == "ok", result
    with np.load(four_devices / "sweep.npz") as z:
        four = {k: z[k] for k in z.files}
    _same(base_result.columns, four)


def test_two_processes_write_the_same_file(tmp_path, capsys):
    """The multi-host path (jax.distributed, global arrays, process_allgather) on localhost."""
    import socket

    with socket.socket() as sock:
        sock.bind(("localhost", 0))
        port = sock.getsockname()[1]
    args = ["sweep", "--samples", "24", "--chunk", "8", "--float64", "--t-final", str(T),
            "--worst", "0", "--random", "0", "--no-plot", "--quiet"]
    env = dict(os.environ, JAX_PLATFORMS="cpu")  # XLA_FLAGS as this process's (conftest)
    procs = [subprocess.Popen(
        [sys.executable, "-m", "dscjax.cli.main", *args, "--out", str(tmp_path / "two"),
         "--coordinator", f"localhost:{port}", "--num-processes", "2", "--process-id", str(i)],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in (0, 1)]
    errs = [p.communicate(timeout=600)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], errs
    assert "2 device(s) (cpu), 2 process(es)" in errs[0]
    assert cli([*args, "--out", str(tmp_path / "one")]) == 0
    capsys.readouterr()
    one = (tmp_path / "one" / "results.npz").read_bytes()
    assert one == (tmp_path / "two" / "results.npz").read_bytes()


def test_sample_tables():
    ranges = (Range(Param("a"), 0.0, 1.0, num=3), Range(Param("b"), 10.0, 20.0, num=2))
    grid = Grid().draw(ranges, 0, 0)
    np.testing.assert_array_equal(grid, [[0, 10], [0, 20], [0.5, 10], [0.5, 20], [1, 10],
                                         [1, 20]])
    r2 = (Range(Param("a"), 0.0, 1.0), Range(Param("b"), -2.0, 2.0))
    lhs = LatinHypercube().draw(r2, 50, 3)
    for j, (lo, hi) in enumerate([(0, 1), (-2, 2)]):  # one sample in each of the 50 strata
        strata = np.floor((lhs[:, j] - lo) / (hi - lo) * 50).astype(int)
        assert sorted(strata) == list(range(50))
    np.testing.assert_array_equal(lhs, LatinHypercube().draw(r2, 50, 3))  # seeded
    assert not np.array_equal(lhs, LatinHypercube().draw(r2, 50, 4))


def test_the_default_threshold_rule_says_why_it_left_the_nominal_error():
    from dscjax.cli.sweep import default_threshold

    cols = {"diverged": np.array([False, False, True, False]),
            "linf_error_window": np.array([0.1, 0.3, np.nan, 0.2])}  # median of the tracked: 0.2
    assert default_threshold(False, 0.05, cols) == (0.1, "2 x nominal")
    assert default_threshold(False, 0.0, cols) == (
        0.4, "2 x median (the nominal setup's windowed error is 0)")
    assert default_threshold(True, np.nan, cols) == (
        0.4, "2 x median (the nominal setup diverged)")
    all_diverged = {"diverged": np.ones(2, bool), "linf_error_window": np.full(2, np.nan)}
    assert default_threshold(False, 0.0, all_diverged) == (
        1.0, "1 (the nominal setup's windowed error is 0; every sample diverged)")


def test_cli_writes_results_summary_and_figures(tmp_path, capsys):
    out = tmp_path / "cli"
    code = cli(["sweep", "--samples", "24", "--chunk", "8", "--t-final", str(T),
                "--window-start", "0.25", "--worst", "2", "--random", "1", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "24/24 samples" in err and "steps/s" in err
    lines = [line for line in err.splitlines() if line.startswith("  sweep ")]
    # no ETA from the first round, which compiled (issue 32): one from a round timed alone
    assert "ETA" not in lines[0] and "ETA" in lines[-1], lines
    assert "re-checking" not in err  # float64, the default: nothing to re-check
    for f in ("results.npz", "summary.json", "summary.md", "traces.npz", "hist_linf_window.png",
              "heatmap_linf_window.png", "traces.png", "sweep.json"):
        assert (out / f).exists(), f
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_samples"] == 24
    assert summary["run"]["dtype"] == "float64" and summary["float32_check"] is None
    md = (out / "summary.md").read_text()
    q = summary["quantiles"]["linf_error_window"]
    assert (f"| linf_error_window | {q['min']:.4g} | {q['p01']:.4g} | {q['p05']:.4g} | "
            f"{q['p25']:.4g} | {q['p50']:.4g} |") in md
    assert f"- diverged at every step tried: {summary['n_diverged']} of 24 (" in md
    assert "ran in float64: nothing to re-check" in md
    worst = summary["worst"][0]
    assert f"| {worst['sample']} | " in md.split("## Worst samples that track")[1]
    assert set(summary["quantiles"]) == set(sweep.METRICS)
    assert summary["quantiles"]["linf_error_window"]["p50"] > 0
    assert len(summary["worst"]) == 2 and "hysteresis.lam" in summary["worst"][0]["params"]
    assert max(summary["traces"]["max_rel_diff_resimulated_vs_sweep"].values()) < 1e-9
    assert summary["run"]["window_start"] == 0.25
    with np.load(out / "results.npz") as z:
        assert z["linf_error_window"].shape == (24,)
        assert np.all(z["hysteresis.lam"] > z["hysteresis.psi"])


def _cli_error(args, capsys, tmp_path):
    code = exit_code(["sweep", "--out", str(tmp_path / "never"), *args])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "never" / "chunks").exists()
    return err


@pytest.mark.parametrize("args, field", [
    (["--samples", "0"], "argument --samples: must be an integer >= 1 (got '0')"),
    (["--samples=-5"], "argument --samples: must be an integer >= 1 (got '-5')"),
    (["--chunk", "0"], "argument --chunk: must be an integer >= 1, or \"none\" (got '0')"),
    (["--range", "hysteresis.alpha=1.3:0.7"], "hysteresis.alpha: lower bound > upper bound"),
    (["--range", "hysteresis.alpha=1:1"], "hysteresis.alpha is an empty range"),
    (["--range", "hysteresis.alpha=0%"], "empty range"),
    (["--range", "hysteresis.lam=0.05:0.2"], "hysteresis.lam must stay > hysteresis.psi"),
    (["--range", "hysteresis.lam=1.0:1.4", "--range", "hysteresis.psi=0.5:1.1"],
     "hysteresis.lam must stay > hysteresis.psi"),
    (["--range", "hysteresis.alpha=-0.5:1"], "hysteresis.alpha must be > 0"),
    (["--range", "hysteresis.alhpa=0.5:1"], "unknown parameter 'hysteresis.alhpa'"),
    (["--range", "plant.g=0.5:1"], "vary one element, e.g. plant.g[0]"),
    (["--range", "plant.g[2]=0.5:1"], "index 2 of 'plant.g' is out of range"),
    (["--range", "hysteresis.alpha"], "--range must be PATH=LOW:HIGH"),
    (["--grid", "hysteresis.alpha=0.7:1.3:1"], "number of grid points must be >= 2"),
    (["--grid", "hysteresis.alpha=0.7:1.3"], "--grid hysteresis.alpha must be PATH=LOW:HIGH:NUM"),
    (["--heatmap", "hysteresis.alpha,plant.g[0]"], "--heatmap: 'plant.g[0]' is not swept"),
])
def test_bad_settings_give_one_clear_line(args, field, capsys, tmp_path):
    err = _cli_error(args, capsys, tmp_path)
    assert field in err, err


@pytest.mark.parametrize("table, field", [
    ("samples = 10\nfoo = 1", "unknown key 'sweep.foo'"),
    ("samples = 0", "sweep.samples must be an integer >= 1"),
    ("chunk = 0", "sweep.chunk must be an integer >= 1"),
    ("samples = 1.5", "sweep.samples must be an integer"),
    ("[sweep.ranges]\n\"hysteresis.alpha\" = [1.2, 0.8]", "lower bound > upper bound"),
    ("[sweep.ranges]\nhysteresis.psi = [0.1, 2.0]", "hysteresis.lam must stay >"),
    ("[sweep.ranges]\n\"plant.g[1]\" = [0.5]", "sweep.ranges.plant.g[1] must be [low, high]"),
    ("[sweep.grid]\n\"hysteresis.alpha\" = [0.7, 1.3, 0]", "must be >= 2"),
])
def test_bad_sweep_tables_name_the_field(table, field, capsys, tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[sweep]\n" + table + "\n")
    err = _cli_error(["--config", str(cfg)], capsys, tmp_path)
    assert field in err, err


def test_config_sweep_table_and_gains_file(tmp_path, capsys):
    cfg = tmp_path / "sweep.toml"
    cfg.write_text(textwrap.dedent("""
        [simulation]
        t_final = 0.5
        [sweep]
        seed = 3
        method = "lhs"
        [sweep.ranges]
        "plant.g[1]" = [0.8, 1.2]
        hysteresis.alpha = "20%"
    """))
    gains = tmp_path / "gains.json"
    # a whole config, as `dscjax tune` writes it: only its gains count
    gains.write_text(json.dumps({"controller": {"k": [8.0, 0.5]},
                                 "simulation": {"t_final": 3.0, "dt": 5e-4},
                                 "hysteresis": {"alpha": 2.0}}))
    code = cli(["sweep", "--config", str(cfg), "--gains", str(gains), "--print-config"])
    out = capsys.readouterr().out
    assert code == 0
    assert 'seed = 3' in out and '"plant.g[1]" = [0.8, 1.2]' in out
    assert '"hysteresis.alpha" = [0.8, 1.2]' in out
    from dscjax.cli.main import _available_commands, build_parser
    from dscjax.cli.sweep import load

    args = build_parser(_available_commands()).parse_args(
        ["sweep", "--config", str(cfg), "--gains", str(gains)])
    setup, options, settings = load(args)
    assert options.t_final == 0.5 and settings.seed == 3 and settings.method.name == "lhs"
    np.testing.assert_array_equal(setup.controller.k, [8.0, 0.5])
    assert options.dt == 1e-3 and float(setup.hysteresis.alpha) == 1.0
    gains.write_text(json.dumps({"plant": {"g": [1.0, 1.0]}}))
    with pytest.raises(dscjax.ConfigError, match="no \\[controller\\] table"):
        load(args)


def test_diverged_rows_have_nan_metrics_and_are_counted_apart(tmp_path, capsys):
    # alpha 10 with lam 0.15: classical RK4 at dt = 1e-3 diverges within milliseconds, before
    # the window [0.25, 0.5] s (its windowed error used to read 0.0). With --refine 0 it is
    # reported diverged; by default it is re-run with ETDRK4 and tracks.
    grid = ["sweep", "--grid", "hysteresis.alpha=1:10:2", "--grid", "hysteresis.lam=0.15:3:2",
            "--float64", "--t-final", str(T), "--window-start", "0.25", "--worst", "1",
            "--random", "0", "--no-plot"]
    out = tmp_path / "div"
    code = cli([*grid, "--refine", "0", "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    with np.load(out / "results.npz") as z:
        div = z["diverged"]
        assert div.tolist() == [False, False, True, False]  # alpha 10, lam 0.15
        for m in sweep.METRICS:
            assert np.all(np.isnan(z[m][div])) and np.all(np.isfinite(z[m][~div])), m
        assert np.all(np.isfinite(z["t_diverged"][div]))
        assert z["refinements"].tolist() == [0, 0, 0, 0] and np.all(z["dt_used"] == 1e-3)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_diverged"] == 1 and summary["smallest_dt_tried"] == 1e-3
    assert all(r["metrics"]["linf_error_window"] is None for r in summary["first_diverged"])
    assert summary["quantiles"]["linf_error_window"]["min"] > 0
    assert "diverged at every step tried: 1 of 4" in captured.out  # a result: stdout

    out = tmp_path / "refined"
    assert cli([*grid, "--out", str(out)]) == 0
    captured = capsys.readouterr()
    with np.load(out / "results.npz") as z:
        assert not z["diverged"].any()
        assert z["refinements"].tolist() == [0, 0, 1, 0]  # ETDRK4 at the same dt
        stiff = z["linf_error_window"][2]
        plain = z["linf_error_window"][[0, 1, 3]]
    # the refined row is the ETDRK4 run of that plant; the others are unchanged, bit for bit
    with np.load(tmp_path / "div" / "results.npz") as z:
        np.testing.assert_array_equal(plain, z["linf_error_window"][[0, 1, 3]])
    one = dscjax.simulate(dscjax.params.set_many(
        dscjax.paper_example(), {"hysteresis.alpha": 10.0, "hysteresis.lam": 0.15}), T, 1e-3,
        window_start=0.25, solver="etdrk4", refine=0)
    assert stiff == pytest.approx(float(one.metrics["linf_error_window"]), rel=1e-12)
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["n_tracked"], summary["n_refined"], summary["n_diverged"]) == (3, 1, 0)
    assert "after refinement (a numerically stiff run re-done with ETDRK4 at a smaller step): 1"\
        in captured.out


# -- issue 38: effort and chattering in every verdict; a gains file sweeps its own loop -------

# a sampled controller with a one-sample input delay, 2 s (every step saved in the traces): at
# k_1 = 30 the gains chatter (a limit cycle at the sample rate), at k_1 = 10 they do not; one
# compiled block program serves both tests below (the gains and Ts are traced)
DELAYED = ["--sample-time", "0.001", "--delay", "1", "--t-final", "2", "--no-plot"]


def test_a_sweep_counts_the_chattering_runs_and_gives_the_effort(tmp_path, capsys):
    cfg = tmp_path / "k.toml"
    cfg.write_text("[controller]\nk = [10.0, 5.0]\n")
    out = tmp_path / "chat"
    assert cli(["sweep", "--config", str(cfg), "--grid", "controller.k[0]=10:30:3", *DELAYED,
                "--worst", "3", "--random", "0", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert ("the controller sampled every Ts = 0.001 s with a zero-order hold, its states "
            "advanced by exponential Euler, the plant by RK4 at dt = 0.001 s; input delay 1 "
            "sample(s); no measurement noise") in captured.err
    with np.load(out / "results.npz") as z:
        cols = {k: z[k] for k in z.files}
    with np.load(out / "traces.npz") as z:
        traces = {k: z[k] for k in z.files}
    assert traces["t"].shape == (3, 2001) and not cols["diverged"].any()
    # every row's TV(u) and chattering index against NumPy on its re-simulated trace; the
    # limit cycle amplifies the round-off by which one run differs from a batch's row (XLA
    # fuses them differently) into the third digit, the smooth rows agree to round-off
    for j, sample in enumerate(traces["sample"]):
        tv, index = chattering_numpy(traces["t"][j], traces["u"][j], 1.0)
        rel = 1e-9 if index < 1.5 else 1e-2
        assert cols["tv_u_window"][sample] == pytest.approx(tv, rel=rel)
        assert cols["chattering_index"][sample] == pytest.approx(index, rel=rel)
    index = cols["chattering_index"]
    assert index[0] < 1.5 < index[2]  # k_1 = 10 smooth, k_1 = 30 a limit cycle
    count = int(np.sum(index > 1.5))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["chattering"] == {"metric": "chattering_index", "above": 1.5,
                                     "count": count, "rate": count / 3,
                                     "definition": "docs/numerics.md"}
    tv = summary["quantiles"]["tv_u_window"]
    np.testing.assert_allclose([tv["p50"], tv["p95"], tv["max"]],
                               np.quantile(cols["tv_u_window"], [0.5, 0.95, 1.0]), rtol=1e-12)
    assert summary["run"]["loop"].startswith("the controller sampled every Ts = 0.001 s")
    line = next(x for x in captured.out.splitlines() if x.startswith("  effort on [1, 2] s"))
    shown = [float(x.replace(",", "")) for x in re.findall(
        r"median ([\d.,]+), p95 ([\d.,]+), max ([\d.,]+);", line)[0]]
    np.testing.assert_allclose(shown, [tv["p50"], tv["p95"], tv["max"]], rtol=5e-4)
    chattering = (f"chattering (chattering index above 1.5, docs/numerics.md; diverged samples "
                  f"not counted): {count} of 3 ({100 * count / 3:.2f} %)")
    assert f"  {chattering}" in captured.out
    md = (out / "summary.md").read_text()
    assert f"- {chattering}" in md
    assert "controller sampled every Ts = 0.001 s" in md.split("## Outcome")[0]


def test_a_gains_file_is_swept_in_the_loop_it_was_tuned_as(tmp_path, capsys):
    gains = tmp_path / "gains.json"
    # as `dscjax tune` writes it: a whole config; the sampled controller's keys travel
    gains.write_text(json.dumps({
        "controller": {"k": [10.0, 0.45]},
        "simulation": {"t_final": 7.0, "dt": 5e-4, "sample_time": 0.002, "delay": 1},
        "hysteresis": {"alpha": 2.0}}))
    out = tmp_path / "g"
    assert cli(["sweep", "--gains", str(gains), "--samples", "3", "--t-final", "2",
                "--no-plot", "--worst", "0", "--random", "0", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "controller sampled every Ts = 0.002 s" in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["run"]["sample_time"] == 0.002 and summary["run"]["delay"] == 1
    assert "controller sampled every Ts = 0.002 s" in (out / "summary.md").read_text()
    with np.load(out / "results.npz") as z:
        cols = {k: z[k] for k in z.files}
    # each row is `dscjax.simulate` of its plant with the gains, sampled at 2 ms with the delay
    spec = dscjax.RunSpec.make(2.0, 1e-3, sample_time=0.002, delay=1)
    gains_setup = dscjax.params.set(dscjax.paper_example(), "controller.k",
                                    np.array([10.0, 0.45]))
    for i in range(3):
        plant = dscjax.params.set_many(gains_setup, {
            p: cols[p][i] for p in ("hysteresis.alpha", "hysteresis.lam", "hysteresis.psi")})
        one = dscjax.simulate(plant, spec=spec, throw=False)
        for m in sweep.METRICS:
            assert cols[m][i] == pytest.approx(float(one.metrics[m]), rel=1e-9), m
    # the command line overrides the gains file's loop; a config's loop gives way to it
    from dscjax.cli.main import _available_commands, build_parser
    from dscjax.cli.sweep import load

    cfg = tmp_path / "c.toml"
    cfg.write_text("[simulation]\nsample_time = 0.001\n")
    parse = build_parser(_available_commands()).parse_args
    _, options, _ = load(parse(["sweep", "--config", str(cfg), "--gains", str(gains)]))
    assert (options.sample_time, options.delay, options.dt) == (0.002, 1, 1e-3)
    assert (f"dscjax sweep: note: simulation.sample_time = 0.001 in {cfg} gives way to {gains}'s "
            f"0.002 (the loop the gains were tuned as; --sample-time overrides both)"
            ) in capsys.readouterr().err
    _, options, _ = load(parse(["sweep", "--gains", str(gains), "--sample-time", "0.003"]))
    assert (options.sample_time, options.delay) == (0.003, 1)


def test_the_float32_check_flags_differences_sign_flips_and_lone_nans():
    got = {"a": [1.0, 2.0005], "b": [0.5, -0.25], "c": [np.nan, 1.0], "d": [np.nan, 3.0],
           "e": [4.0, 5.0]}
    ref = {"a": [1.0, 2.0], "b": [0.5, 0.25], "c": [np.nan, 1.0], "d": [1.0, 3.0],
           "e": [4.004, 5.0]}
    trust = sweep.float32_trust(got, ref)
    assert trust["rtol"] == 1e-3
    assert trust["max_rel_diff"] == {"a": pytest.approx(2.5e-4), "b": 2.0, "c": 0.0,
                                     "d": np.inf, "e": pytest.approx(0.004 / 4.004)}
    assert trust["at"] == {"a": 1, "b": 1, "c": 0, "d": 0, "e": 0}
    assert trust["sign_flips"] == ["b"] and trust["untrusted"] == ["b", "d"]
    assert sweep.float32_trust(got, ref, rtol=1e-4)["untrusted"] == ["a", "b", "d", "e"]
