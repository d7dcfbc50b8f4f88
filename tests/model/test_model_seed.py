"""Seed compatibility (issue 2): the lesson's own program (tests/seed_reference.py) is the peer.

Reference numbers: steady-state position variance 1.8711e-4 with white actuator noise and
1.4341e-3 with the AR(1) actuator noise augmented into the state (seed parameters; computed
independently, quoted in issue 2).
"""

import numpy as np
import pytest
from scipy.linalg import solve_discrete_lyapunov

import seed_reference as ref
from noiselab.model import load_model

N = 6000


@pytest.fixture(scope="module")
def lesson():
    return ref.run(N, seed=17)


def test_nominal_recursion_equals_lesson_at_every_k(lesson):
    """seed-nominal is the lesson's prediction model: P_k and S_y,k equal the lesson's recursion."""
    cov = load_model("seed-nominal").predictor().covariance(N)
    P_ref = lesson["P_hist"][1:]
    P = cov.P[1:, :2, :2]
    scale = np.abs(P_ref).max(axis=(1, 2))[:, None, None]
    assert np.max(np.abs(P - P_ref) / scale) < 1e-12
    S_ref = lesson["Syy_hist"][1:]
    assert np.max(np.abs(cov.Sy[1:, 0] - S_ref) / S_ref) < 1e-12


def _augmented_lesson_recursion(n):
    """The lesson's recursion with the AR(1) state augmented (section 7), written out by hand:
    z = [x1, x2, n_a]; x_{k+1} = A x_k + B (rho n_k + e_k) + G w_k; n_{k+1} = rho n_k + e_k."""
    A, B, G = ref.A, ref.B, ref.G
    rho, sa, sw = ref.rho_a, ref.sigma_a_ss, ref.sigma_w
    se2 = (1 - rho**2) * sa**2
    F = np.array([[A[0, 0], A[0, 1], B[0, 0] * rho],
                  [A[1, 0], A[1, 1], B[1, 0] * rho],
                  [0.0, 0.0, rho]])
    ge = np.array([B[0, 0], B[1, 0], 1.0])
    gw = np.array([G[0, 0], G[1, 0], 0.0])
    Q = se2 * np.outer(ge, ge) + sw**2 * np.outer(gw, gw)
    P = np.zeros((3, 3))
    out = np.zeros((n, 3, 3))
    for k in range(n - 1):
        P = F @ P @ F.T + Q
        out[k + 1] = P
    return out


def test_seed_recursion_equals_augmented_transcription_at_every_k():
    cov = load_model("seed").predictor().covariance(N)
    P_ref = _augmented_lesson_recursion(N)[1:]
    P = cov.P[1:]
    scale = np.abs(P_ref).max(axis=(1, 2))[:, None, None]
    assert np.max(np.abs(P - P_ref) / scale) < 1e-12
    # S_y,k = C P_k C^T + R_v + R_q + R_b,k with R_b,k = k Q_b, Q_b = std^2 Ts (seed section 4)
    k = np.arange(N)
    expect = cov.P[:, 0, 0] + ref.sigma_v**2 + ref.delta_q**2 / 12 + k * ref.sigma_bias_rw**2 * ref.Ts
    np.testing.assert_allclose(cov.Sy[:, 0], expect, rtol=1e-12)
    np.testing.assert_allclose(cov.parts["sensor.bias_walk"][:, 0], k * 0.002**2 * 0.01, rtol=1e-12)


def test_reference_steady_state_numbers():
    white = load_model("seed-nominal").predictor().steady_state()
    ar1 = load_model("seed").predictor().steady_state()
    assert white.P[0, 0] == pytest.approx(1.8711e-4, rel=5e-5)
    assert ar1.P[0, 0] == pytest.approx(1.4341e-3, rel=5e-5)
    # the Lyapunov solution is the limit of the recursion, and solves its own equation
    A, B, G = ref.A, ref.B, ref.G
    Pw = solve_discrete_lyapunov(A, ref.sigma_w**2 * G @ G.T + ref.sigma_a_ss**2 * B @ B.T)
    np.testing.assert_allclose(white.P, Pw, rtol=1e-10)
    assert _augmented_lesson_recursion(20000)[-1][0, 0] == pytest.approx(ar1.P[0, 0], rel=1e-6)
    assert ar1.bias_var_rate[0] == pytest.approx(0.002**2)


def test_lesson_sample_path_reproduced_bit_for_bit(lesson):
    """Fed the lesson's own random draws, noiselab's seed scenario produces the lesson's y."""
    mdl = load_model("seed")
    normals = ref.seed_normals_layout(lesson["draws"])
    rec = mdl.simulate(N, normals=normals)
    assert np.array_equal(rec.y[1:, 0], lesson["y"][1:])
    np.testing.assert_allclose(rec.x[1:], lesson["x"][1:], rtol=0, atol=1e-13)
    st = mdl.stepper(normals=normals)
    ys = np.array([st.step()[3][0] for _ in range(N)])
    assert np.array_equal(ys[1:], lesson["y"][1:])


def test_lesson_seven_fold_story():
    """The lesson's demo compares var(y) of the measured signal with the nominal prediction;
    on the same data the ratio is about 7 (the command response, the AR(1) color and the walk
    are missing from the prediction)."""
    lesson = ref.run(N, seed=17)
    burn = 1000
    emp = np.var(lesson["y"][burn:], ddof=1)
    pred_lesson = np.mean(lesson["Syy_hist"][burn:])
    cov = load_model("seed-nominal").predictor().covariance(N)
    assert np.mean(cov.Sy[burn:, 0]) == pytest.approx(pred_lesson, rel=1e-12)
    assert 5 < emp / pred_lesson < 10
