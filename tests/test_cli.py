"""`dscjax simulate`: the files a user gets, --print-config, variants, float32."""

import json

import numpy as np
import pytest

from dscjax.cli.main import main


def test_simulate_writes_trajectory_metrics_and_plot(tmp_path):
    out = tmp_path / "run"
    assert main(["simulate", "--t-final", "2", "--out", str(out)]) == 0
    data = np.load(out / "trajectory.npz")
    n_t = 2001
    assert data["t"].shape == (n_t,) and data["x"].shape == (n_t, 2)
    for key in ("u", "w", "yr"):
        assert data[key].shape == (n_t,)
    assert data["t"][-1] == 2.0 and data["t"][1] == 1e-3
    m = json.loads((out / "metrics.json").read_text())
    for key in ("linf_error", "l2_error", "max_abs_u"):
        assert np.isfinite(m[key])
    assert m["linf_error"] == np.abs(data["x"][:, 0] - data["yr"]).max()
    assert (out / "trajectory.png").stat().st_size > 10_000


def test_print_config_round_trips(tmp_path, capsys):
    assert main(["simulate", "--print-config"]) == 0
    text = capsys.readouterr().out
    cfg = tmp_path / "c.toml"
    cfg.write_text(text.replace("alpha = 1.0", "alpha = 2.0"))
    assert main(["simulate", "--config", str(cfg), "--print-config"]) == 0
    assert "alpha = 2.0" in capsys.readouterr().out


def test_variant_and_float32_flags(tmp_path):
    out = tmp_path / "v"
    assert main(["simulate", "--t-final", "1", "--variant", "no_dhat", "--float32",
                 "--save-every", "10", "--no-plot", "--out", str(out)]) == 0
    data = np.load(out / "trajectory.npz")
    assert data["x"].dtype == np.float32 and data["x"].shape == (101, 2)
    assert np.all(data["d_hat"] == 0.0)
    assert json.loads((out / "metrics.json").read_text())["dtype"] == "float32"


def test_diverged_simulation_writes_null_metrics_not_zeros(tmp_path, capsys):
    # dt = 0.02 diverges at t = 0.04 s, before the window [1, 2] s starts
    out = tmp_path / "div"
    assert main(["simulate", "--t-final", "2", "--dt", "0.02", "--no-plot",
                 "--out", str(out)]) == 3
    m = json.loads((out / "metrics.json").read_text())
    assert m["diverged"] is True and m["t_diverged"] == pytest.approx(0.04)
    for key in ("linf_error", "linf_error_window", "l2_error_window", "max_abs_u"):
        assert m[key] is None, key
    captured = capsys.readouterr()
    text = captured.out + captured.err
    assert "after t0: 0" not in text and "diverged at t = 0.04 s" in text
