"""Theorem 1 along trajectories: the Lyapunov function (44), the gain rules (55) and (60), the
constant e_M (61) and the bounds (65), (71) and (72).

    lv = theory.lyapunov(setup, dscjax.simulate(setup, 20.0, 1e-3))   # V(t) of (44), its terms

V of (44) is 1/2 sum_(i<n) (S_i^2/g_i + theta~_gi^2/gamma_gi + phi~_i^2/gamma_phi_i + y_(i+1)^2)
+ 1/2 (beta zeta~^2/gamma_zeta + theta~_n^2/gamma_gn + d~^2/gamma_d + S_n^2), with the
estimation errors (34)-(38) against the TRUE plant (`Truth`) and the filter errors (33);
docs/theory.md lists every reading of the garbled text. Functions of one state (`b_at`,
`filter_errors_at`, ...) are pure in (setup, truth, t, X) and compose with vmap and jvp; the host
functions (`lyapunov`, `check`, ...) evaluate them at a `Trajectory`'s saved points in
fixed-size chunks (one compilation whatever the length). M_(i+1) of (59) has no closed form:
`check` uses the maximum measured on the run, so its bounds are data-driven estimates.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import operator
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import xla
from dscjax.closed_loop import State, prepared, vector_field
from dscjax.simulate import canonical
from dscjax.validation import ConfigError

# the (rate, leakage) pairs whose products (55) sets to 2 alpha_0, and their names in reports
PAIRS = (("gamma_g", "eta", "eta_{i} gamma_g{i}"), ("gamma_phi", "sigma", "sigma_{i} gamma_phi{i}"),
         ("gamma_zeta", "eta_zeta", "eta_zeta gamma_zeta"), ("gamma_d", "eta_d", "eta_d gamma_d"))

_CHUNK = 2048  # points per vmapped chunk when evaluating along a trajectory


class Truth(NamedTuple):
    """The true values the DSC's estimates estimate, and the constants of Assumption 4."""

    theta: jax.Array  # (n,) theta_i/g_i for i < n (15), (21), then theta_n (36)
    phi: jax.Array  # (n-1,) 1/g_i (15), (21)
    beta: jax.Array  # () lam g_n (10), lam the hysteresis's slope (5)
    zeta: jax.Array  # () 1/beta (27)
    d: jax.Array  # () the bound d of |d_n| (12)
    g: jax.Array  # (n,) the true g_i
    g_max: jax.Array  # () max g_i


def default_d(setup, t=None) -> jax.Array:
    """The default bound of |d_n| (11)-(12): g_n (lam - psi)/alpha + max |dbar|, from the limits
    (7)-(8) of d_1. An early d_1 outside its asymptotes can exceed it: `check` tests (12).
    max_t |dbar(t)| is |dbar_amp| + |dbar_bias| (+ the waveform's `max_abs`) for the built-in
    plants; for other plants the maximum over the times `t`."""
    plant = setup.plant
    if hasattr(plant, "dbar_amp") and hasattr(plant, "dbar_bias"):
        dbar = jnp.abs(jnp.asarray(plant.dbar_amp)) + jnp.abs(jnp.asarray(plant.dbar_bias))
        if getattr(plant, "disturbance", None) is not None:
            dbar = dbar + plant.disturbance.max_abs()
    elif t is None:
        raise ConfigError(f"{type(plant).__name__}: max |dbar| is not known in closed form; pass "
                          "the times to take it over, or give d explicitly")
    else:
        dbar = jnp.max(jnp.abs(jax.vmap(plant.dbar)(jnp.asarray(t))))
    return jnp.asarray(plant.g)[-1] * setup.hysteresis.d1_bound() + dbar


def truth(setup, d=None, t=None) -> Truth:
    """The true parameters of `setup`'s plant and hysteresis, in the controller's
    parameterisation (15), (21), (27), with d = `default_d` unless given."""
    plant = setup.plant
    g, theta = jnp.asarray(plant.g), jnp.asarray(plant.theta)
    theta_g = jnp.concatenate([theta[:-1] / g[:-1], theta[-1:]])
    # lam of w = lam u + d_1(u) (5), in beta (10)
    beta = setup.hysteresis.effective_slope() * g[-1]
    d = default_d(setup, t) if d is None else d
    return Truth(theta=theta_g, phi=1.0 / g[:-1], beta=beta, zeta=1.0 / beta,
                 d=jnp.asarray(d, g.dtype), g=g, g_max=jnp.max(g))


class Terms(NamedTuple):
    """The terms of V (44) at one state (a leading time axis along a trajectory)."""

    surface: jax.Array  # (n,) S_i^2/(2 g_i) for i < n, S_n^2/2
    filter: jax.Array  # (n-1,) y_(i+1)^2/2, the filter errors (33)
    theta: jax.Array  # (n,) theta~_gi^2/(2 gamma_gi) for i < n, theta~_n^2/(2 gamma_gn)
    phi: jax.Array  # (n-1,) phi~_i^2/(2 gamma_phi_i)
    zeta: jax.Array  # () beta zeta~^2/(2 gamma_zeta)
    d: jax.Array  # () d~^2/(2 gamma_d)

    def total(self):
        # the vectors (surface, filter, theta, phi) summed over i, then the scalars
        return sum(jnp.sum(v, -1) for v in self[:4]) + self.zeta + self.d


TERM_NAMES = Terms._fields


def _over_rate(err, gamma):
    """err^2 / (2 gamma), and 0 where gamma = 0: an estimate that does not adapt is a constant
    whose infinite term is left out (V' unchanged). Double `where`: no NaN gradients."""
    on = gamma > 0
    return jnp.where(on, 0.5 * err * err / jnp.where(on, gamma, 1.0), 0.0)


def _require_dsc(controller):
    if getattr(controller, "kind", None) != "dsc":
        raise ConfigError(f"the Lyapunov function (44) is the DSC's: controller.kind must be "
                          f"'dsc' (got {getattr(controller, 'kind', type(controller).__name__)!r})")


def filter_errors_at(setup, t, X: State):
    """(y (n-1,), S (n,)) at one state of a prepared setup: the filter errors y_(i+1) =
    z_(i+1) - x_(i+1)d (33) = -tau_(i+1) z_(i+1)' (42) by the filters (18), (24)."""
    ctrl = setup.controller
    _, info = ctrl.law(X.ctrl, X.x, t, setup.plant, setup.reference)
    return -ctrl.tau * info.extra.z_dot, info.S


def _terms_y_s(setup, tr: Truth, t, X: State):
    """(the terms of V (44), y, S) at one state, from one evaluation of the law."""
    y, s = filter_errors_at(setup, t, X)
    ctrl, c = setup.controller, X.ctrl
    n = s.shape[0]
    surface = jnp.stack([0.5 * s[i] * s[i] / tr.g[i] for i in range(n - 1)]
                        + [0.5 * s[n - 1] * s[n - 1]])
    terms = Terms(
        surface=surface,
        filter=0.5 * y * y,
        theta=_over_rate(c.theta_hat - tr.theta, ctrl.gamma_g),
        phi=_over_rate(c.phi_hat - tr.phi, ctrl.gamma_phi),
        zeta=tr.beta * _over_rate(c.zeta_hat - tr.zeta, ctrl.gamma_zeta),
        d=_over_rate(c.d_hat - tr.d, ctrl.gamma_d),
    )
    return terms, y, s


def b_at(setup, t, X: State):
    """B_(i+1) of (43): y_(i+1)' = -y_(i+1)/tau_(i+1) + B_(i+1), i.e. -x_(i+1)d' along the
    closed loop; computed as y' + y/tau with y' by one jvp."""
    dX, _ = vector_field(t, X, setup)
    y, y_dot = jax.jvp(lambda tt, XX: filter_errors_at(setup, tt, XX)[0], (t, X),
                       (jnp.ones_like(t), dX))
    return y_dot + y / setup.controller.tau


def robust_slack(ctrl, tr: Truth, s_n, d_hat):
    """What the robust term in use leaves over in the proof's step (48)-(49): with the
    controller's own switching function r and |.| surrogate a, d (|S_n| - a(S_n)) + d_hat
    (a(S_n) - S_n r(S_n)) (0 for sgn(S_n), the proof's term; <= d_hat w/4 for sat(S_n/w))."""
    a = ctrl._abs_surface(s_n)
    return tr.d * (jnp.abs(s_n) - a) + d_hat * (a - s_n * ctrl._robust(s_n))


class LyapunovTerms(NamedTuple):
    """V(t) of (44) and its terms at a trajectory's saved times (leading axis T), NumPy arrays;
    the terms' fields read as attributes too (lv.surface: (T, n), ...)."""

    t: jax.Array  # (T,)
    V: jax.Array  # (T,) the sum of every term
    terms: Terms  # with a leading time axis
    y: jax.Array  # (T, n-1) the filter errors (33)
    truth: Truth  # the true parameters used

    def __getattr__(self, name):  # lv.surface, lv.theta, ...: the terms' fields
        if name in TERM_NAMES:
            return getattr(self.terms, name)
        raise AttributeError(name)

    def arrays(self) -> dict[str, np.ndarray]:
        """{'t', 'V', and one array per term}, the keys of `lyapunov.npz`."""
        return {k: np.asarray(getattr(self, k)) for k in ("t", "V", *TERM_NAMES, "y")}


def _chunked(fn, args, t, X, chunk=_CHUNK):
    """fn(*args, t_j, X_j) at every point j, vmapped over fixed-size chunks (the last one
    padded: `xla.tiles`): one compilation per chunk size, whatever the trajectory's length."""
    n_pts = int(np.shape(t)[0])
    leaves, tree = jax.tree.flatten((t, X))
    outs = [_chunk_eval(fn, args, *jax.tree.unflatten(tree, part))
            for part in zip(*(xla.tiles(np.asarray(a), chunk) for a in leaves), strict=True)]
    return jax.tree.map(lambda *a: np.concatenate(a)[:n_pts], *outs)


@functools.partial(xla.jit, lean=True, static_argnums=0)
def _chunk_eval(fn, args, t, X):
    return jax.vmap(lambda tt, XX: fn(*args, tt, XX))(t, X)


def _along(fn, setup, traj, d=None):
    """(prepared setup, truth, fn(setup, truth, t, X) at every saved point) of a single DSC
    trajectory `traj` of the unprepared `setup`."""
    _require_dsc(setup.controller)
    s = prepared(canonical(setup))
    if np.ndim(traj.t) != 1:
        raise ConfigError("expected a single trajectory (traj.t of shape (T,)); for a batch, "
                          "index one member first")
    t = np.asarray(traj.t)
    tr = truth(s, d, t)
    return s, tr, _chunked(fn, (s, tr), t, State(x=traj.x, h=traj.h, ctrl=traj.ctrl))


def lyapunov(setup, traj, d=None) -> LyapunovTerms:
    """V(t) of eq. (44) and its terms (`LyapunovTerms`) along a single DSC trajectory `traj`
    of the unprepared `setup`, at its saved times; `d` the bound of |d_n| in d~ = d_hat - d
    (38), default `default_d`.

    Example:
        >>> import dscjax
        >>> from dscjax.reproduce import theory
        >>> setup = dscjax.paper_example()
        >>> traj = dscjax.simulate(setup, t_final=1.0, dt=1e-3, save_every=100)
        >>> lv = theory.lyapunov(setup, traj)
        >>> lv.V.shape, lv.surface.shape
        ((11,), (11, 2))
    """
    _, tr, (terms, y, _) = _along(_terms_y_s, setup, traj, d)
    return LyapunovTerms(t=np.asarray(traj.t), V=np.asarray(terms.total()), terms=terms, y=y,
                         truth=tr)


def lyapunov_rate(setup, traj, d=None):
    """(V, dV/dt) at the saved points: the exact derivative of (44) along the vector field."""
    pts = _along(_point_checks, setup, traj, d)[2]
    return pts["V"], pts["V_dot"]


def gains_55(controller, alpha0, hold: Literal["eta", "gamma"] = "eta"):
    """The controller with the gains of eq. (55) for alpha_0: k_1 = 3 + alpha_0/g_min, k_i =
    3 1/4 + alpha_0/g_min, k_n = 1/4 + alpha_0, every eta gamma pair = 2 alpha_0, keeping the
    leakages (hold="eta": e_M then does not depend on alpha_0, the paper's remark after (72))
    or the rates (hold="gamma"); tau is left alone (`tau_60`)."""
    if hold not in ("eta", "gamma"):
        raise ConfigError(f"hold must be 'eta' or 'gamma' (got {hold!r})")
    _require_dsc(controller)
    n = np.shape(controller.k)[0]
    a = jnp.asarray(alpha0, jnp.result_type(controller.k))
    g_min = controller.g_min
    changes = {"k": jnp.stack([3.0 + a / g_min] + [3.25 + a / g_min] * (n - 2) + [0.25 + a])}
    for rate, leakage, _ in PAIRS:
        held, changed = (leakage, rate) if hold == "eta" else (rate, leakage)
        changes[changed] = 2.0 * a / jnp.asarray(getattr(controller, held))
    return dataclasses.replace(controller, **changes)


def tau_60(alpha0, M, mu):
    """Filter time constants of eq. (60): 1/tau_(i+1) = 1/4 + M_(i+1)^2/(2 mu) + alpha_0."""
    M = jnp.asarray(M)
    return 1.0 / (0.25 + M * M / (2.0 * mu) + alpha0)


def e_M(controller, tr: Truth):
    """The constant e_M of eq. (61) (printed "M") without the mu term; c_(i+1) is the
    PREPARED controller's offset (x_(i+1)(0) under (68))."""
    c = controller
    n = np.shape(c.k)[0]
    return (jnp.sum(c.eta * tr.theta ** 2) / 2 + jnp.sum(c.sigma * tr.phi ** 2) / 2
            + jnp.sum(c.c ** 2) / 4 + c.eta_zeta * tr.beta * tr.zeta ** 2 / 2
            + c.eta_d * tr.d ** 2 / 2 + (n - 1) * c.eps / (2 * c.g_min) + c.eps / 2)


def v0_69(controller, tr: Truth):
    """V(0) of eq. (69): V under the L-inf initialisation (67)-(68), where S_i(0) = 0,
    y_(i+1)(0) = 0 and every estimate is 0, so only the estimation errors remain."""
    c = controller
    return 0.5 * (jnp.sum(tr.theta ** 2 / c.gamma_g) + jnp.sum(tr.phi ** 2 / c.gamma_phi)
                  + tr.beta * tr.zeta ** 2 / c.gamma_zeta + tr.d ** 2 / c.gamma_d)


def bound_65(t, V0, C, alpha0):
    """Eq. (65): V(t) <= C/(2 alpha_0) + (V(0) - C/(2 alpha_0)) exp(-2 alpha_0 t),
    C = e_M + (n-1) mu/2 (+ the data-driven slacks of `check`)."""
    ss = bound_71(C, alpha0)
    return ss + (V0 - ss) * np.exp(-2.0 * alpha0 * np.asarray(t))


def bound_71(C, alpha0):
    """Eq. (71): V(t) <= C/(2 alpha_0), valid when (70) V(0) < C/(2 alpha_0) holds."""
    return C / (2.0 * alpha0)


def bound_72(C, alpha0, g_max):
    """Eq. (72): ||S_1||_inf <= sqrt(g_max C/alpha_0) (from S_1^2/(2 g_1) <= V and (71))."""
    return math.sqrt(g_max * C / alpha0)


def gain_rules(controller, M, mu) -> list[tuple]:
    """The gain rules (55) and (60) as the inequalities the proof uses, value >= sum(base) +
    alpha_0/scale: (gain, value, rule, base, scale) for each gain, in the controller's order."""
    c = jax.tree.map(np.asarray, controller)
    n, g_min = np.shape(c.k)[0], float(c.g_min)
    M = np.asarray(M, float)
    rows = [("k_1", c.k[0], "3 + alpha_0/g_min", (3.0,), g_min)]
    rows += [(f"k_{i + 1}", c.k[i], "3 1/4 + alpha_0/g_min", (3.25,), g_min)
             for i in range(1, n - 1)]
    rows += [(f"k_{n}", c.k[n - 1], "1/4 + alpha_0", (0.25,), 1.0)]
    for rate, leakage, name in PAIRS:
        products = np.atleast_1d(getattr(c, leakage) * getattr(c, rate))
        rows += [(name.format(i=i + 1), v, "2 alpha_0", (), 0.5) for i, v in enumerate(products)]
    rows += [(f"1/tau_{i + 2}", 1.0 / c.tau[i], f"1/4 + M^2/(2 mu) + alpha_0 (M = {M[i]:.3g}, "
              f"mu = {mu:.3g})", (0.25, M[i] ** 2 / (2.0 * mu)), 1.0) for i in range(n - 1)]
    return rows


def certified_alpha0(controller, M, mu) -> tuple[float, dict]:
    """(alpha_0, {gain: the alpha_0 it allows}): the largest alpha_0 for which the gains
    satisfy (55) and (60) (`gain_rules`); 1/tau_(i+1) is named tau_(i+1)."""
    allows = {gain.removeprefix("1/"): float(functools.reduce(operator.sub, base, value) * scale)
              for gain, value, _, base, scale in gain_rules(controller, M, mu)}
    return min(allows.values()), allows


def _point_checks(setup, tr, t, X):
    """Everything `check` needs at one state: one vector field, one jvp of (V, y)."""
    dX, obs = vector_field(t, X, setup)

    def v_y_s(tt, XX):
        terms, y, s = _terms_y_s(setup, tr, tt, XX)
        return terms.total(), y, s

    (v, y, s), (v_dot, y_dot, _) = jax.jvp(v_y_s, (t, X), (jnp.ones_like(t), dX))
    ctrl, hyst, u = setup.controller, setup.hysteresis, obs.u
    # d_n = g_n d_1(u) + dbar(t) = g_n (w - lam u) + dbar(t) (5), (11)
    d_n = tr.g[-1] * (hyst.output(u, X.h) - hyst.effective_slope() * u) + setup.plant.dbar(t)
    return dict(V=v, V_dot=v_dot, B=y_dot + y / ctrl.tau,
                slack=robust_slack(ctrl, tr, s[-1], X.ctrl.d_hat), d_n=d_n)


# the conclusions of Theorem 1 that `check` tests, and the hypotheses of the proof it tests on
# the run (Delta_i <= rho_i and g_i >= g_min hold by construction for the built-in plants)
STATEMENTS = {
    "(63)": "V' <= -2 alpha_0 V + C at every step",
    "(65)": "V(t) <= C/(2 alpha_0) + (V(0) - C/(2 alpha_0)) exp(-2 alpha_0 t)",
    "(70)": "V(0) < C/(2 alpha_0)",
    "(71)": "V(t) <= C/(2 alpha_0)",
    "(72)": "||S_1||_inf <= sqrt(g_max C/alpha_0)",
}
ASSUMPTIONS = {
    "(12)": "|d_n(t)| <= d",
    "(59)": "|B_(i+1)(t)| <= M_(i+1)",
}


def check(setup, traj, alpha0, mu, M=None, d=None) -> dict:
    """Every statement of Theorem 1 along one DSC trajectory (saved at every step for the
    maxima to be over every step) of the unprepared `setup`, for `alpha0` and `mu` of (59)-(60).

    C = e_M (61) + (n-1) mu/2 + the maximum of `robust_slack` on the run. M (n-1,) of (59)
    defaults to max_t |B_(i+1)| measured on the run (the bounds are then data-driven
    estimates); d to `default_d`. Returns plain floats/arrays: V0, V_max, S1_inf, e_M, C,
    slack, M, M_measured, d, d_n_max, the bounds (65) (T,), (71), (72), V, V' (T,), B (T, n-1)
    of (43), the worst margins of (63) and (65) (<= 0 when they hold), `holds` ({`STATEMENTS`
    key: bool}) and `assumptions` ({`ASSUMPTIONS` key: bool}).
    """
    s, tr, pts = _along(_point_checks, setup, traj, d)
    V, V_dot = pts["V"], pts["V_dot"]
    M_meas = np.max(np.abs(pts["B"]), axis=0)
    M_used = M_meas if M is None else np.asarray(M, float)
    slack = float(np.max(pts["slack"]))
    eM = float(e_M(s.controller, tr))
    C = eM + (setup.order - 1) * mu / 2 + slack
    V0, V_max = float(V[0]), float(V.max())
    S1 = float(np.max(np.abs(np.asarray(traj.S)[:, 0])))
    b65, b71 = bound_65(traj.t, V0, C, alpha0), bound_71(C, alpha0)
    b72 = bound_72(C, alpha0, float(tr.g_max))
    # (63): V' <= -2 alpha_0 V + C; relative to the size of the terms compared
    r63 = V_dot + 2 * alpha0 * V - C
    d_n_max, dval = float(np.max(np.abs(pts["d_n"]))), float(tr.d)
    assumptions = {"(12)": d_n_max <= dval, "(59)": bool(np.all(M_meas <= M_used * (1 + 1e-12)))}
    holds = {
        "(63)": bool(np.all(r63 <= 1e-9 * (np.abs(V_dot) + 2 * alpha0 * V + C))),
        "(65)": bool(np.all(V <= b65 * (1 + 1e-9))),
        "(70)": V0 < b71,
        "(71)": V_max <= b71,
        "(72)": S1 <= b72,
    }
    return dict(
        alpha0=float(alpha0), mu=float(mu), V0=V0, V_max=V_max, S1_inf=S1, e_M=eM,
        C=C, slack=slack, M=M_used, M_measured=M_meas, d=dval, d_n_max=d_n_max,
        bound_71=b71, bound_72=b72, bound_65=b65, V=V, V_dot=V_dot, B=pts["B"],
        margin_63=float(np.max(r63)), margin_65=float(np.max(V - b65)),
        v0_69=float(v0_69(s.controller, tr)), holds=holds, assumptions=assumptions,
    )

