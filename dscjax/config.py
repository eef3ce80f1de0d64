"""TOML (or JSON) configuration <-> (Setup, RunSpec).

A config file maps onto the same dataclasses the Python API takes: one table per model
([plant], [hysteresis], [controller], [reference]) whose keys are the model's field names, plus
[simulation]. A file only needs the keys it changes: it is laid over the embedded default (the
paper's example). Changing a section's kind (e.g. `reference.kind = "smooth_step"`) starts
that section from the new class's defaults. Unknown sections or keys, wrong types and
out-of-range values are `ConfigError`s naming the field. Nothing in a config is ever evaluated
as code, and pickles are never read. A file's tables are read by `dscjax.configfile`; the
built-in loops are `dscjax.examples`' (their callers import them from here too).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from dscjax import disturbance, settings, validation
from dscjax.closed_loop import Setup
from dscjax.configfile import read as read  # re-exported (config.read)
from dscjax.controllers.backstepping import Backstepping
from dscjax.controllers.dsc import DSC
from dscjax.examples import example as example  # re-exported (the module docstring)
from dscjax.examples import hysteresis_example as hysteresis_example
from dscjax.examples import order_n_example as order_n_example
from dscjax.examples import paper_example
from dscjax.hysteresis import MODELS
from dscjax.plant import PaperPlant, StrictFeedback
from dscjax.reference import MultiSine, Sine, SmoothStep
from dscjax.runspec import RunSpec, Simulation
from dscjax.validation import ConfigError

# kind name -> class, per section; the key that selects the kind.
REGISTRY: dict[str, dict[str, type]] = {
    "plant": {PaperPlant.kind: PaperPlant, StrictFeedback.kind: StrictFeedback},
    "hysteresis": {c.kind: c for c in MODELS},
    "controller": {DSC.kind: DSC, Backstepping.kind: Backstepping},
    "reference": {Sine.kind: Sine, SmoothStep.kind: SmoothStep, MultiSine.kind: MultiSine},
}
# the key that selects a section's kind: "family" for the plant, "kind" for every other section
# and sub-model
KIND_KEY = {"plant": "family"}
# Fields that hold a model of their own, by config path, written as a sub-table
# ([plant.disturbance]); absent (None) unless the config gives the table.
SUBMODELS: dict[str, dict[str, type]] = {"plant.disturbance": disturbance.KINDS}


# -- Setup -> dict -> TOML ----------------------------------------------------------------------


def _plain(value):
    a = np.asarray(value)
    dtype = a.dtype if a.dtype.kind == "f" else np.float64
    return np.vectorize(lambda x: validation.shortest(x, dtype), otypes=[object])(a).tolist()


def model_to_dict(section: str, model) -> dict[str, Any]:
    out: dict[str, Any] = {KIND_KEY.get(section, "kind"): type(model).kind}
    for f in dataclasses.fields(model):
        value = getattr(model, f.name)
        if f"{section}.{f.name}" in SUBMODELS:
            if value is not None:  # a sub-table; TOML has no null, so None is left out
                out[f.name] = model_to_dict(f"{section}.{f.name}", value)
            continue
        out[f.name] = value if f.metadata.get("static") else _plain(value)
    return out


def to_dict(setup: Setup, spec: RunSpec | None = None) -> dict[str, Any]:
    """The config of a setup and run as plain data (keys left to a rule or absent omitted)."""
    spec = spec or RunSpec.make()
    sim = {k: v for k, v in spec.to_table().items() if v is not None}
    return {"simulation": sim} | {section: model_to_dict(section, getattr(setup, section))
                                  for section in REGISTRY}


# One line per key of the printed config: meaning, equation, allowed range.
DOCS: dict[str, str] = settings.meanings(Simulation, "simulation.") | {
    "plant.family": "paper (eq. 73) or strict_feedback (order-n family)",
    "plant.g": "g_i > 0, eq. (1) (unknown to the controller)",
    "plant.theta": "theta_i, eq. (1) (unknown to the controller)",
    "plant.x0": "initial state x(0)",
    "plant.rho1": "rho_1 = rho1 (known bound of |Delta_1|)",
    "plant.rho2": "rho_2 = rho2 (x_1^2 + x_2^2)",
    "plant.delta1": "Delta_1 = delta1 sin(x_2)",
    "plant.delta2": "Delta_2 = delta2 (x_1^2 + x_2^2) sin^3(delta_freq t)",
    "plant.delta_freq": "frequency of the sin^3 factor of Delta",
    "plant.dbar_amp": "disturbance dbar = dbar_amp sin(dbar_freq t) + dbar_bias",
    "plant.dbar_freq": "frequency [rad/s] of the disturbance dbar",
    "plant.dbar_bias": "constant part of the disturbance dbar",
    "plant.disturbance.kind": "waveform added to dbar: fourier | spline (dscjax.disturbance)",
    "plant.disturbance.coefficients": "fourier: [c_0, a_1..a_K, b_1..b_K], dbar += c_0 + "
                                      "sum a_j cos(2 pi j t/P) + b_j sin(2 pi j t/P)",
    "plant.disturbance.period": "fourier: period P [s] > 0",
    "plant.disturbance.knots": "spline: values at K equally spaced times on [0, horizon] "
                               "(monotone cubic, stays within the knots)",
    "plant.disturbance.horizon": "spline: time [s] of the last knot > 0",
    "plant.f_quad": "f_i += f_quad_i x_i^2",
    "plant.f_sin": "f_i += f_sin_i sin(x_i)",
    "plant.f_cross": "f_i += f_cross_i x_(i-1) x_i",
    "plant.rho_const": "rho_i = rho_const_i + rho_quad_i (x_1^2 + ... + x_i^2)",
    "plant.rho_quad": "see rho_const: the known bounds rho_i of |Delta_i| (Assumption 2)",
    "plant.delta_sin": "Delta_i += delta_sin_i sin(x_(i+1))",
    "plant.delta_quad": "Delta_i += delta_quad_i (x_1^2 + ... + x_i^2) sin^3(delta_freq t)",
    "hysteresis.kind": "backlash (eq. 4) | pi | gpi | bouc_wen (docs/hysteresis.md)",
    "hysteresis.alpha": "alpha > 0",
    "hysteresis.lam": "lambda > psi",
    "hysteresis.psi": "psi",
    "hysteresis.w0": "w(0) (not given in the paper)",
    "hysteresis.smooth_delta": "width of the smooth |u'| when smooth = true",
    "hysteresis.smooth": "replace |u'| by sqrt(u'^2 + delta^2) - delta",
    "hysteresis.p0": "w = p0 u + sum_j p_j z_j; p0 >= 0",
    "hysteresis.r": "play thresholds r_1 < ... < r_N, >= 0",
    "hysteresis.p": "play weights p_1..p_N >= 0",
    "hysteresis.z0": "plays' outputs before t = 0: one number or N",
    "hysteresis.envelope_left": "gpi: [a, b, c, d] of gamma_l = a tanh(b u + c) + d (u rising)",
    "hysteresis.envelope_right": "gpi: [a, b, c, d] of gamma_r (u falling)",
    "hysteresis.a": "bouc_wen: w = a u + b h; a > 0",
    "hysteresis.b": "bouc_wen: weight of h",
    "hysteresis.A": "bouc_wen: h' = A u' - beta |u'| |h|^(n-1) h - gamma u' |h|^n",
    "hysteresis.beta": "bouc_wen: beta + gamma > 0",
    "hysteresis.gamma": "bouc_wen",
    "hysteresis.n": "bouc_wen: exponent n >= 1",
    "hysteresis.h0": "bouc_wen: h(0)",
    "controller.kind": "dsc (Section 2) or backstepping (baseline)",
    "controller.k": "gains k_1..k_n > 0, eqs. (16), (22), (30)",
    "controller.tau": "filter time constants tau_2..tau_n > 0, eqs. (18), (24)",
    "controller.c": "surface offsets c_2..c_n, eqs. (19), (25)",
    "controller.gamma_g": "adaptation rates gamma_g1..gamma_gn > 0, eqs. (17), (23), (31)",
    "controller.eta": "leakages eta_1..eta_n >= 0, eqs. (17), (23), (31)",
    "controller.gamma_phi": "adaptation rates gamma_phi1..gamma_phi(n-1) > 0",
    "controller.sigma": "leakages sigma_1..sigma_(n-1) >= 0",
    "controller.gamma_zeta": "adaptation rate of zeta_hat > 0, eq. (29)",
    "controller.eta_zeta": "leakage of zeta_hat >= 0, eq. (29)",
    "controller.gamma_d": "adaptation rate of d_hat > 0, eq. (32)",
    "controller.eta_d": "leakage of d_hat >= 0, eq. (32)",
    "controller.eps": "epsilon > 0 of the rho^2/(2 eps) terms",
    "controller.g_min": "known lower bound of g_i (Assumption 4)",
    "controller.theta_hat0": "initial theta_hat_g1..theta_hat_g(n-1), theta_hat_n",
    "controller.phi_hat0": "initial phi_hat_1..phi_hat_(n-1)",
    "controller.zeta_hat0": "initial zeta_hat",
    "controller.d_hat0": "initial d_hat",
    "controller.sat_width": "sgn(S_n) -> sat(S_n / sat_width)",
    "controller.smooth_delta": "corner width of the smooth saturation (robust_term = smooth)",
    "controller.linf_decay_time": "decay time [s] of the y_r offset of init = linf",
    "controller.variant": "full | no_dhat | no_dhat_no_zeta (no hysteresis compensation)",
    "controller.robust_term": "sat | sgn | smooth",
    "controller.init": "paper | linf (eqs. 67-68) | zero_surfaces",
    "controller.g_nom": "backstepping: nominal g_j of the chain rule for alpha_i' (> 0)",
    "reference.kind": "sine | smooth_step | multisine",
    "reference.amplitude": "y_r = amplitude sin(frequency t + phase) + offset",
    "reference.frequency": "[rad/s]",
    "reference.phase": "[rad]",
    "reference.offset": "constant added to y_r",
    "reference.height": "smooth step: y_r = initial + height (1 + tanh((t - t_step)/rise_time))/2",
    "reference.t_step": "smooth step: time [s] of the middle of the step",
    "reference.rise_time": "smooth step: rise time [s] > 0",
    "reference.initial": "smooth step: y_r before the step",
    "reference.amplitudes": "multisine: y_r = sum_j amplitudes_j sin(frequencies_j t + phases_j)",
    "reference.frequencies": "multisine: [rad/s]",
    "reference.phases": "multisine: [rad]",
}


@dataclasses.dataclass(frozen=True)
class Omitted:
    """A key left out of the config, printed commented out with the value it takes."""

    value: Any


DOC_COLUMN = 38  # where a key's meaning starts, after its value


def dumps_toml(d: Mapping[str, Mapping[str, Any]], header: str = "",
               docs: Mapping[str, str] | None = None) -> str:
    """TOML text of config tables, written by tomlkit: each key followed by its meaning as a
    comment (`docs`: config path -> text, default DOCS); a value wrapped in `Omitted` is
    written as a comment (the key is valid, its default is a rule); None as "none"."""
    import tomlkit

    doc = tomlkit.document()
    for line in header.splitlines():
        doc.add(tomlkit.comment(line))
    for name, table in d.items():
        doc.add(name, _toml_table(name, table, DOCS if docs is None else docs))
    return tomlkit.dumps(doc)


def _toml_table(path: str, table: Mapping[str, Any], docs: Mapping[str, str]):
    import tomlkit

    out = tomlkit.table()
    for key, value in sorted(table.items(), key=lambda item: isinstance(item[1], Mapping)):
        if isinstance(value, Mapping):  # (sub-tables last: TOML reads a key after one into it)
            out.add(key, _toml_table(f"{path}.{key}", value, docs))
            continue
        text = docs.get(f"{path}.{key}")
        if isinstance(value, Omitted):
            line = key if value.value is None else tomlkit.dumps({key: _data(value.value)}).strip()
            out.add(tomlkit.comment(f"{line:<{DOC_COLUMN - 2}s}# {text}" if text else line))
            continue
        out.add(key, _data(value))
        if text:
            item = out.item(key)
            width = len(tomlkit.dumps({key: item}).strip())
            item.comment(text)
            item.trivia.comment_ws = " " * max(1, DOC_COLUMN - width)
    return out


def _data(value):
    """A value as TOML data: NumPy scalars and arrays as Python numbers and lists, tuples as
    lists, None as "none" (TOML has no null)."""
    if value is None:
        return "none"
    if isinstance(value, np.ndarray | np.generic):
        value = value.tolist()
    if isinstance(value, list | tuple):
        return [_data(v) for v in value]
    return value


# -- dict / file -> Setup -----------------------------------------------------------------------


def _coerce(section: str, name: str, value, static: bool, default):
    field = f"{section}.{name}"
    if static:
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise ConfigError(f"{field} must be true or false (got {value!r})")
            return value
        return validation.string(value, field)
    where, item = _find(value, bool | np.bool_ | str | dict)
    if where is not None:  # NumPy would read true as 1.0 and "10" as the number 10
        validation.not_boolean(item, f"{field}{where}")
        detail = validation.got(item)
        if where:  # "controller.k[1] is a string, 'a'"
            detail = f"{field}{where} is {detail.removeprefix('got ')}"
        raise ConfigError(f"{field} must be a number or a list of numbers, not text in quotes "
                          f"({detail})")
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(
            f"{field} must be a number or a list of numbers (got {value!r})") from None
    return float(a) if a.ndim == 0 else a


def _find(value, kinds, where: str = "") -> tuple[str | None, Any]:
    """(index, item) of the first item of a value read from TOML or JSON that is one of
    `kinds` (index "" for the value itself, "[1]", "[0][2]"), or (None, None). NumPy would read
    `true` as the number 1.0 and "10" as 10: a config that says `k = [10.0, true]` is a
    mistake, not k_2 = 1."""
    if isinstance(value, kinds):
        return where, value
    for i, item in enumerate(value if isinstance(value, list | tuple) else ()):
        found = _find(item, kinds, f"{where}[{i}]")
        if found[0] is not None:
            return found
    return None, None


def _model(field: str, table: Mapping[str, Any], base):
    """The model of kind `table[kind_key]` (default: `base`'s) at `field`, its keys read over
    `base`; a model held by a field (`SUBMODELS`) from its sub-table, the same way."""
    kinds = REGISTRY.get(field) or SUBMODELS[field]
    kind_key = KIND_KEY.get(field, "kind")
    kind = validation.table(table, field).get(kind_key, getattr(base, "kind", None))
    validation.one_of(kind, f"{field}.{kind_key}", tuple(kinds))
    cls = kinds[kind]
    if base is not None and type(base) is not cls:
        # a controller of another kind lends the gains the two share (the DSC's k, gamma_*,
        # eta, ... for backstepping); a model with nothing in common starts from nothing
        convert = getattr(cls, "from_dsc", None)
        base = convert(base) if convert is not None and base.kind == "dsc" else None
    fields = {f.name: f for f in dataclasses.fields(cls)}
    validation.known_keys(table, field, [kind_key, *fields])
    values = {}
    for name, f in fields.items():
        default = getattr(base, name) if base is not None else f.default
        if name in table and f"{field}.{name}" in SUBMODELS:
            values[name] = _model(f"{field}.{name}", table[name], default)
        elif name in table:
            value = _coerce(field, name, table[name], bool(f.metadata.get("static")), default)
            coefficients = getattr(cls, "coefficients_name", None)
            values[name] = np.atleast_1d(value) if name == coefficients else value
        elif base is not None:
            values[name] = default
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(f"{field}.{name} is required for {field}.{kind_key} = {kind!r}")
    return cls(**values)


# the tables of the commands' own settings: a config may hold them (a printed config, a
# gains.json, identified.toml); each command reads its own, the model ignores them
COMMAND_TABLES = ("tuning", "sweep", "worst", "identify")


def from_dict(d: Mapping[str, Any], base: Setup | None = None,
              base_spec: RunSpec | None = None) -> tuple[Setup, RunSpec]:
    """(Setup, RunSpec) from a config dict laid over `base` (default: the paper's example) and
    `base_spec` (default: the defaults of [simulation]); a command's table (`COMMAND_TABLES`)
    is left to its command."""
    if base is None:
        base = paper_example(dtype=np.float64)
    allowed = ("simulation", *REGISTRY)
    for key in d:  # each section is checked a table where it is read
        if key not in allowed + COMMAND_TABLES:
            raise ConfigError(f"unknown section '{key}' (allowed: "
                              f"{', '.join(allowed + COMMAND_TABLES)})")
    models = {s: _model(s, d.get(s, {}), getattr(base, s)) for s in allowed[1:]}
    return Setup(**models), RunSpec.from_table(d.get("simulation", {}), base=base_spec)


def to_toml(setup: Setup, spec: RunSpec | None = None, header: str = "", extra=None,
            docs: Mapping[str, str] | None = None) -> str:
    """The config as TOML with every key, each described (`--print-config`). [simulation] keys
    whose default is a rule (window_start, save_every) are printed commented out with the
    value the rule gives for this horizon and step; optional keys left out, commented out.
    `extra`: further tables ({name: table}, e.g. a command's [sweep]) printed after these."""
    spec = spec or RunSpec.make()
    applied = spec.describe()  # a key left to a rule: the value the rule gives, commented out
    sim = {k: Omitted(applied.get(k)) if v is None else v for k, v in spec.to_table().items()}
    return dumps_toml({**to_dict(setup, spec), "simulation": sim, **(extra or {})},
                      header=header, docs=docs)
