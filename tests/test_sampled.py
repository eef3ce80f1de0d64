"""The digital controller (issue 27): a held input moves each hysteresis model along its own
curve (`Hysteresis.jump`), checked against closed forms written here from the models' equations."""

import math

import numpy as np
import pytest

from dscjax.hysteresis import Backlash, BoucWen, GeneralizedPI, PrandtlIshlinskii

STEPS = [(0.0, 2.0, 0.3), (1.5, -2.0, 0.1), (-0.4, -0.1, -0.6), (0.7, 0.7, 0.2)]


@pytest.mark.parametrize("u_from, u_to, w", STEPS)
def test_backlash_jump_is_the_closed_form_of_dw_du(u_from, u_to, w):
    a, lam, psi = 1.3, 1.432, 0.105
    got = float(Backlash(alpha=a, lam=lam, psi=psi).jump(u_from, u_to, w))
    # dw/du = s a (lam u - w) + psi, s = sgn(u_to - u_from), solved by hand:
    # w = lam u - s (lam - psi)/a + C e^(-s a u)
    s = 1.0 if u_to >= u_from else -1.0
    c = (w - lam * u_from + s * (lam - psi) / a) * math.exp(s * a * u_from)
    want = lam * u_to - s * (lam - psi) / a + c * math.exp(-s * a * u_to)
    assert got == pytest.approx(want, rel=1e-13, abs=1e-14)


def test_plays_jump_to_the_clamp_at_the_new_input():
    r, p, z = np.array([0.0, 0.3, 0.8]), np.array([0.5, 0.2, 0.4]), np.array([0.1, -0.5, 0.6])
    pi = PrandtlIshlinskii(p0=0.3, r=r, p=p)
    for u_to in (-1.0, 0.05, 0.4, 2.0):
        np.testing.assert_allclose(pi.jump(0.2, u_to, z), np.clip(z, u_to - r, u_to + r),
                                   rtol=0, atol=0)
    el, er = np.array([3.0, 0.4, -0.1, 0.05]), np.array([2.5, 0.5, 0.2, -0.1])
    gpi = GeneralizedPI(envelope_left=el, envelope_right=er, p0=0.3, r=r, p=p)
    for u_to in (-1.0, 0.4, 2.0):
        lo = el[0] * np.tanh(el[1] * u_to + el[2]) + el[3] - r
        hi = er[0] * np.tanh(er[1] * u_to + er[2]) + er[3] + r
        np.testing.assert_allclose(gpi.jump(0.2, u_to, z), np.maximum(lo, np.minimum(hi, z)),
                                   rtol=1e-15, atol=1e-15)


@pytest.mark.parametrize("u_from, u_to, h, rel", [(0.0, 0.05, 0.3, 1e-14), (0.5, 0.3, 0.9, 1e-10),
                                                  (0.0, 2.0, 0.3, 1e-6)])
def test_bouc_wen_jump_is_the_closed_form_for_n_1(u_from, u_to, h, rel):
    A, beta, gamma = 1.0, 0.6, 0.15
    got = float(BoucWen(A=A, beta=beta, gamma=gamma, n=1.0).jump(u_from, u_to, h))
    # n = 1, h > 0 along the step: dh/du = A - (beta s + gamma) h
    s = 1.0 if u_to >= u_from else -1.0
    k = beta * s + gamma
    want = A / k + (h - A / k) * math.exp(-k * (u_to - u_from))
    assert want > 0
    # RK4 in u over JUMP_SUBSTEPS substeps: round-off for the steps of a sampled input
    # (|du| well below 1), O(du^4) for a step across the whole loop
    assert got == pytest.approx(want, rel=rel)
