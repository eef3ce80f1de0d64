"""The built-in closed loops (`--example NAME`, `example`): the paper's Section 4
(`paper_example`; every reading of the paper is a setting, docs/paper-readings.md), the order-n
family (`order_n_example`), the paper's loop behind another hysteresis model
(`hysteresis_example`) and with the backstepping baseline.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from dscjax.closed_loop import Setup
from dscjax.controllers.backstepping import with_backstepping
from dscjax.controllers.dsc import DSC
from dscjax.hysteresis import MODELS, Backlash
from dscjax.params import cast
from dscjax.plant import PaperPlant, StrictFeedback
from dscjax.reference import Sine
from dscjax.validation import ConfigError


def paper_plant() -> PaperPlant:
    """Eq. (73): g = (1, 1), theta = (0.1, 0), f_1 = x_1^2, f_2 = 0, Delta_1 = 0.2 sin(x_2),
    Delta_2 = 0.1 (x_1^2 + x_2^2) sin^3(t), rho = (0.2, 0.1 (x_1^2 + x_2^2)), x(0) = (0.08, 0.1)."""
    return PaperPlant(g=np.array([1.0, 1.0]), theta=np.array([0.1, 0.0]),
                      x0=np.array([0.08, 0.1]))


def paper_family_plant() -> StrictFeedback:
    """Eq. (73) as a member of the order-n `StrictFeedback` family (same plant, more terms)."""
    return StrictFeedback.zeros(
        2, g=[1.0, 1.0], theta=[0.1, 0.0], x0=[0.08, 0.1], f_quad=[1.0, 0.0],
        rho_const=[0.2, 0.0], rho_quad=[0.0, 0.1], delta_sin=[0.2, 0.0], delta_quad=[0.0, 0.1])


def paper_hysteresis() -> Backlash:
    """alpha = 1, lam = 1.432, psi = 0.105; w(0) = 0 (not given in the paper)."""
    return Backlash(alpha=1.0, lam=1.432, psi=0.105, w0=0.0)


def paper_controller(variant: str = "full", robust_term: str = "sat", init: str = "paper") -> DSC:
    """Section 4's gains. The text prints "k_1 = 10, k_1 = 0.45": read k_2 = 0.45 (= 1/4 + alpha_0
    with alpha_0 = 0.2, eq. 55). gamma_g2, eta_2, theta_hat_2(0) are not given and irrelevant
    (f_2 = 0): 8, 0.01, 0. c_2 = x_2(0) = 0.1; sat width 0.01."""
    return DSC(
        k=np.array([10.0, 0.45]), tau=np.array([0.01]), c=np.array([0.1]),
        gamma_g=np.array([8.0, 8.0]), eta=np.array([0.01, 0.01]),
        gamma_phi=np.array([8.0]), sigma=np.array([0.01]),
        gamma_zeta=8.0, eta_zeta=0.01, gamma_d=8.0, eta_d=0.01, eps=0.01, g_min=1.0,
        theta_hat0=np.array([0.05, 0.0]), phi_hat0=np.array([1.0]), zeta_hat0=0.5, d_hat0=1.0,
        sat_width=0.01, variant=variant, robust_term=robust_term, init=init)


def paper_example(variant: str = "full", robust_term: str = "sat", init: str = "paper",
                  dtype=None) -> Setup:
    """The closed loop of the paper's Section 4 with y_r = sin t.

    Args:
        variant: "full", "no_dhat" or "no_dhat_no_zeta" (the two readings of "without
            considering hysteresis" in Fig. 2).
        robust_term: "sat" (the paper's sat(S_2/0.01)), "sgn" or "smooth".
        init: "paper" (Section 4's initial values), "linf" (67-68), "zero_surfaces".
        dtype: dtype of every number (default: JAX's default float, float64 when x64 is on).

    Example:
        >>> import dscjax
        >>> setup = dscjax.paper_example()
        >>> setup.order
        2
    """
    setup = Setup(plant=paper_plant(), hysteresis=paper_hysteresis(),
                  controller=paper_controller(variant, robust_term, init), reference=Sine())
    return _cast(setup, dtype)


def _cast(setup: Setup, dtype) -> Setup:
    """`cast` to `dtype`, default JAX's default float (float64 when x64 is on)."""
    import jax.numpy as jnp

    return cast(setup, dtype if dtype is not None else jnp.zeros(()).dtype)


def order_n_example(n: int, tau: float = 0.05, k: float = 4.0, dtype=None,
                    **controller_changes) -> Setup:
    """A tracking example of order n >= 2 from the StrictFeedback family (tracks for n <= 4
    with these uniform gains; higher orders need their own, as `controller_changes`).

    Plant (q_i = x_1^2 + ... + x_i^2): g_i = 1, theta_i = 0.1, f_i = 0.2 x_i^2 + 0.2 sin(x_i)
    (+ 0.05 x_(i-1) x_i for i >= 2), rho_i = 0.05 + 0.02 q_i, Delta_i = 0.05 sin(x_(i+1)) +
    0.02 q_i sin^3 t; the paper's hysteresis; y_r = sin t. Order n >= 3 is stiff (u'(0) grows
    like 1/tau^(n-1); docs/numerics.md), so x_i(0) = y_r^(i-1)(0), the estimates start at their
    nominal values, S_i(0) = 0 ("zero_surfaces"), tau_i = `tau` and k_i = `k`.
    """
    if n < 2:
        raise ValueError(f"order n must be >= 2 (got {n})")
    m = n - 1
    x0 = np.round(np.sin(0.5 * np.pi * np.arange(n)), 12)  # 0, 1, 0, -1, ...
    plant = StrictFeedback.zeros(
        n, g=np.ones(n), theta=np.full(n, 0.1), x0=x0, f_quad=np.full(n, 0.2),
        f_sin=np.full(n, 0.2), f_cross=np.concatenate([[0.0], np.full(m, 0.05)]),
        rho_const=np.full(n, 0.05), rho_quad=np.full(n, 0.02), delta_sin=np.full(n, 0.05),
        delta_quad=np.full(n, 0.02))
    ctrl = DSC(
        k=np.full(n, k), tau=np.full(m, tau), c=np.zeros(m), gamma_g=np.full(n, 1.0),
        eta=np.full(n, 0.01), gamma_phi=np.full(m, 1.0), sigma=np.full(m, 0.01),
        gamma_zeta=1.0, eta_zeta=0.01, gamma_d=1.0, eta_d=0.01, eps=0.5, g_min=1.0,
        theta_hat0=np.zeros(n), phi_hat0=np.ones(m), zeta_hat0=1.0 / 1.432, d_hat0=0.0,
        sat_width=0.05, init="zero_surfaces")
    setup = Setup(plant=plant, hysteresis=paper_hysteresis(),
                  controller=dataclasses.replace(ctrl, **controller_changes), reference=Sine())
    return _cast(setup, dtype)


def hysteresis_example(kind: str, dtype=None) -> Setup:
    """The paper's loop (plant, DSC gains, reference) with the `kind` hysteresis model at its
    class defaults, whose large-amplitude slope and offset are close to the paper's
    (docs/hysteresis.md): "pi", "gpi" or "bouc_wen"; "backlash" is `paper_example` itself."""
    setup = paper_example(dtype=np.float64)
    if kind != "backlash":
        setup = setup.replace(hysteresis={c.kind: c for c in MODELS}[kind]())
    return _cast(setup, dtype)


def example(name: str, dtype=None) -> Setup:
    """A built-in closed loop by name, as `--example NAME` selects it.

    - "paper": the paper's Section 4 (`paper_example`), the default;
    - "backstepping": the paper's plant with the adaptive backstepping baseline (the DSC's
      gains, `Backstepping.from_dsc`);
    - "order-N" (N >= 2): the order-n family of `order_n_example` (S_i(0) = 0, tau = 0.05);
    - "pi", "gpi", "bouc_wen": the paper's loop behind another actuator (`hysteresis_example`).

    Example:
        >>> import dscjax
        >>> dscjax.config.example("order-3").order
        3
    """
    if name == "paper":
        return paper_example(dtype=dtype)
    if name == "backstepping":
        return with_backstepping(paper_example(dtype=dtype))
    if name.startswith("order-") and name[6:].isdigit() and int(name[6:]) >= 2:
        return order_n_example(int(name[6:]), dtype=dtype)
    if name in ("pi", "gpi", "bouc_wen"):
        return hysteresis_example(name, dtype=dtype)
    raise ConfigError(f"--example must be paper, backstepping, order-N with N >= 2 (e.g. "
                      f"order-4), pi, gpi or bouc_wen (got {name!r})")
