"""Where programs run (issue 28): the device choice and the sweep's block size as functions of
a device list and free memory (stand-in devices: no accelerator is needed), placement on real
(forced host) devices, `--device gpu` without a GPU, `--version`, and the device benchmark."""

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np
import pytest

import dscjax
from dscjax import device
from dscjax.cli.main import main

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True, eq=False)
class Dev:
    """A stand-in for a jax Device: what `dscjax.device` reads of one."""

    platform: str
    id: int = 0
    process_index: int = 0
    stats: dict | None = None

    def memory_stats(self):
        return self.stats


CPU = Dev("cpu")
GPUS = (Dev("gpu", 0), Dev("gpu", 1))
GPU_MACHINE = (CPU, *GPUS)


def test_auto_runs_small_work_on_the_cpu_and_large_batches_on_every_gpu():
    limit = device.crossover(2)
    assert device.crossover(16) > limit > 1  # more cores: the CPU keeps larger batches
    one = device.choose("auto", 1, GPU_MACHINE, n_cores=2)
    assert one.device is CPU and one.devices == (CPU,)
    assert one.reason == f"auto: one trajectory, fewer than the ~{limit:,} a GPU needs to be faster"
    below = device.choose("auto", limit - 1, GPU_MACHINE, n_cores=2)
    assert below.device is CPU
    big = device.choose("auto", limit, GPU_MACHINE, n_cores=2)
    assert big.device is GPUS[0] and big.devices == GPUS
    assert str(big) == (f"gpu x2 (auto: {limit:,} trajectories, at least the ~{limit:,} a GPU "
                        f"needs to be faster)")
    assert device.choose("auto", limit, GPU_MACHINE, n_cores=16).device is CPU


def test_auto_without_an_accelerator_uses_every_cpu_device():
    cpus = tuple(Dev("cpu", i) for i in range(4))
    choice = device.choose("auto", 10**6, cpus)
    assert choice.device is cpus[0] and choice.devices == cpus
    assert str(choice) == "cpu x4 (auto: JAX sees no GPU)"


def test_asked_devices_and_the_callers_default_win_over_the_rule():
    assert device.choose("cpu", 10**6, GPU_MACHINE).device is CPU
    assert device.choose("gpu", 1, GPU_MACHINE).devices == GPUS
    mine = device.choose("auto", 1, GPU_MACHINE, preferred=GPUS[1])
    assert mine.device is GPUS[1] and mine.devices == (GPUS[1], GPUS[0])
    assert mine.reason == "auto: the caller's jax.default_device"
    given = device.choose(GPUS[1], 1, GPU_MACHINE)
    assert given.device is GPUS[1] and given.reason == "as given"


def test_the_device_of_this_process_runs_a_single_program():
    other, mine = Dev("gpu", 0, process_index=1), Dev("gpu", 1, process_index=0)
    choice = device.choose("gpu", 1, (CPU, other, mine))
    assert choice.device is mine and choice.devices == (other, mine)


def test_gpu_without_one_and_unknown_kinds_are_refused_in_one_line():
    with pytest.raises(dscjax.ConfigError) as err:
        device.choose("gpu", 1, (CPU, Dev("cpu", 1)), field="--device")
    assert str(err.value) == (
        "--device must be one of 'auto', 'cpu' on this machine (got 'gpu', but JAX sees no "
        "GPU: cpu x2); on a GPU machine install JAX's CUDA wheels: pip install -e \".[cuda]\"")
    with pytest.raises(dscjax.ConfigError, match=r"^simulation.device must be one of 'auto', "
                       r"'cpu', 'gpu' \(got 'tpu'\)$"):
        device.choose("tpu", 1, GPU_MACHINE)


def test_the_cpu_block_is_todays_rule():
    # about 16,384 rows, blocks evenly filled (7 x 14,336 for 100,000); memory does not enter
    assert device.auto_chunk(100_000, CPU) == device.auto_chunk(100_000) == 14_336
    assert device.auto_chunk(24, CPU) == 24 and device.auto_chunk(16_385, CPU) == 8_448
    assert device.auto_chunk(100_000, CPU, free=10**6, per_row=1e6) == 14_336


def test_an_accelerator_block_fills_its_free_memory():
    gpu = GPUS[0]
    # an 80 GB card, 2 KB a row: the cap, blocks evenly filled
    assert device.auto_chunk(10**6, gpu, 80 * 10**9, 2048) == 500_224
    assert device.auto_chunk(4 * 2**19, gpu, 80 * 10**9, 2048) == device.MAX_BLOCK
    assert device.auto_chunk(10**6, gpu, 80 * 10**9, 2048) >= 131_072
    # 0.5 x 1 GB / 4 KB = 122,070 rows fit: at most 2^16 per block, 16 blocks of 62,500
    assert device.auto_chunk(10**6, gpu, 10**9, 4096) == 62_720
    assert device.auto_chunk(2**16 * 3, gpu, 10**9, 4096) == 2**16
    # a batch smaller than the cap is one block; over 4 devices, one block each
    assert device.auto_chunk(100_000, gpu, 80 * 10**9, 2048) == 100_096
    assert device.auto_chunk(100_000, gpu, 80 * 10**9, 2048, n_devices=4) == 25_088
    # memory unknown: the default block; too little memory: the smallest block
    assert device.auto_chunk(10**6, gpu, None, 2048) == 125_184
    assert device.auto_chunk(10**6, gpu, 10**6, 4096) == device.MIN_BLOCK


def test_free_memory_and_the_footprint_of_a_row():
    full = Dev("gpu", stats={"bytes_limit": 80 * 10**9, "bytes_in_use": 10**9})
    assert device.free_bytes(full) == 79 * 10**9
    assert device.free_bytes(Dev("gpu")) is None
    assert device.free_bytes(jax.devices("cpu")[0]) is None  # the CPU does not say
    rows = 4096
    compiled = jax.jit(lambda x: 2.0 * x).lower(
        jax.ShapeDtypeStruct((rows, 3), np.float32)).compile()
    per_row = device.per_row_bytes(compiled, rows)
    assert 24 <= per_row < 25  # 12 bytes in and 12 out per row, a few bytes of temporaries

    class NoAnalysis:
        def memory_analysis(self):
            return None

    assert device.per_row_bytes(NoAnalysis(), rows) is None


def test_describe_names_the_backends_jax_sees():
    lines = device.describe()
    assert lines[0] == f"jax {jax.__version__}, default backend {jax.default_backend()}"
    n = len(jax.devices("cpu"))
    assert f"cpu: {n} device{'s' if n > 1 else ''} (cpu)" in lines


def test_runs_are_placed_on_the_chosen_device_of_four_forced_host_devices(four_devices):
    # tests/four_devices.py's `placement`: "auto" takes all four devices, the first for one
    # run; simulate and simulate_batch run on the device given or the caller's default
    result = json.loads((four_devices / "results.json").read_text())["placement"]
    assert result == "ok", result


ARGV = {
    "simulate": ["simulate", "--t-final", "0.2"],
    "sweep": ["sweep", "--samples", "8", "--t-final", "0.2"],
    "tune": ["tune", "--t-final", "0.2"],
    "worst-case": ["worst-case", "--range", "hysteresis.alpha=30%", "--t-final", "0.2"],
    "reproduce": ["reproduce", "--t-final", "0.2"],
    "stability": ["stability", "--t-final", "0.2"],
    "hysteresis": ["hysteresis", "--t-final", "0.2"],
}


@pytest.mark.skipif(any(d.platform != "cpu" for d in device.visible()),
                    reason="this machine has an accelerator")
@pytest.mark.parametrize("command", list(ARGV))
def test_device_gpu_without_a_gpu_is_one_line_exit_2_and_writes_nothing(command, tmp_path,
                                                                        capsys):
    out = tmp_path / "out"
    code = main([*ARGV[command], "--device", "gpu", "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == "", captured
    n = len(jax.devices("cpu"))
    assert captured.err == (
        f"dscjax {command}: error: --device must be one of 'auto', 'cpu' on this machine (got "
        f"'gpu', but JAX sees no GPU: cpu x{n}); on a GPU machine install JAX's CUDA wheels: "
        f"pip install -e \".[cuda]\"\n")
    assert not out.exists()


@pytest.mark.skipif(any(d.platform != "cpu" for d in device.visible()),
                    reason="this machine has an accelerator")
def test_a_config_asking_for_a_gpu_runs_on_the_cpu_with_a_note(tmp_path, capsys):
    # issue 38 item 6b: a gains.json of `tune --device gpu` runs everywhere (the device is a
    # preference of the run it was written for); typed on the command line it is still refused
    cfg = tmp_path / "gains.json"
    cfg.write_text(json.dumps({"simulation": {"device": "gpu"},
                               "controller": {"k": [10.0, 0.45]}}))
    out = tmp_path / "o"
    code = main(["simulate", "--config", str(cfg), "--t-final", "0.2", "--no-plot", "--out",
                 str(out)])
    err = capsys.readouterr().err.splitlines()
    assert code == 0, err
    assert err[0] == (f"dscjax simulate: note: simulation.device = 'gpu' in {cfg}: no GPU "
                      f"here; running on the CPU")
    assert err[1].endswith("; on cpu (auto: JAX sees no GPU)"), err
    assert json.loads((out / "metrics.json").read_text())["diverged"] is False
    from dscjax.cli.main import _available_commands, build_parser
    from dscjax.cli.sweep import load

    parse = build_parser(_available_commands()).parse_args
    assert load(parse(["sweep", "--config", str(cfg)]))[1].device == "auto"
    assert capsys.readouterr().err == (f"dscjax sweep: note: simulation.device = 'gpu' in "
                                       f"{cfg}: no GPU here; running on the CPU\n")
    code = main(["simulate", "--config", str(cfg), "--device", "gpu", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("dscjax simulate: error: --device must be one of "
                                        "'auto', 'cpu' on this machine (got 'gpu'"), err


def test_the_banner_says_where_the_run_went_and_why(tmp_path, capsys):
    code = main(["simulate", "--t-final", "0.2", "--device", "cpu", "--no-plot", "--out",
                 str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 0, err
    assert err.splitlines()[0].endswith("the continuous loop (RK4 at dt = 0.001 s); on cpu "
                                        "(as asked)"), err


def test_the_loop_words_name_the_plant_solver():
    from dscjax.runspec import RunSpec, loop_words

    continuous = RunSpec.make(t_final=1.0, dt=1e-3, solver="etdrk4")
    assert loop_words(continuous) == "the continuous loop (ETDRK4 at dt = 0.001 s)"
    sampled = RunSpec.make(t_final=1.0, dt=1e-3, solver="etdrk4", sample_time=2e-3)
    assert "the plant by ETDRK4 at dt = 0.001 s; input delay 0" in loop_words(sampled)


def test_version_lists_the_backends_and_devices(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines == [f"dscjax {dscjax.__version__}", *device.describe()]


def test_a_resume_keeps_the_block_size_the_sweep_started_with(tmp_path):
    from dscjax.sweep import SweepSettings, run_sweep

    setup = dscjax.paper_example(dtype=np.float32)
    out = tmp_path / "s"
    first = run_sweep(setup, SweepSettings(samples=16, chunk=8), t_final=0.2, dt=1e-3,
                      out_dir=out)
    again = run_sweep(setup, SweepSettings(samples=16), t_final=0.2, dt=1e-3, out_dir=out,
                      resume=True)
    assert first.info["chunk"] == again.info["chunk"] == 8 and again.info["samples_run"] == 0
    assert again.info["placement"] == "cpu (auto: JAX sees no GPU)"


def test_the_device_benchmark_runs_at_small_sizes():
    written = ROOT / "results" / "bench" / "device-quick.json"  # the harness's place
    written.unlink(missing_ok=True)
    proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "bench_device.py"),
                           "--quick"], capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    record = json.loads(written.read_text())
    assert record["quick"] is True
    cases = {(r["case"], r["device"]) for r in record["rows"]}
    assert ("batch throughput", "cpu") in cases and ("one trajectory (float64)", "cpu") in cases
    batch = next(r for r in record["rows"] if r["case"] == "batch throughput")
    assert batch["dscjax"] > 0 and batch["vmap+scan"] > 0
