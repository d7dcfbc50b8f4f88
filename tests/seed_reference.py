"""The seed lesson's Python program (section 10, Chapter17_Lesson4.py), transcribed as the peer.

Only two changes from the lesson: the random draws are recorded (so noiselab can be fed the very
same numbers) and N / the seed are parameters. Everything else, including the order of the draws
and the covariance recursion, is the lesson's.
"""

import numpy as np

m, c, k = 1.2, 0.35, 4.0
Ts = 0.01
A_c = np.array([[0.0, 1.0], [-k / m, -c / m]])
B_c = np.array([[0.0], [1.0 / m]])
G_c = np.array([[0.0], [1.0 / m]])
C = np.array([[1.0, 0.0]])
A = np.eye(2) + Ts * A_c
B = Ts * B_c
G = Ts * G_c
sigma_w, sigma_v, sigma_bias_rw, delta_q, rho_a, sigma_a_ss = 0.20, 0.01, 0.002, 0.001, 0.97, 0.08
Qw = np.array([[sigma_w**2]])
Qa = np.array([[sigma_a_ss**2]])
Rv = np.array([[sigma_v**2]])
Rq = np.array([[delta_q**2 / 12.0]])


def run(N=6000, seed=17, record_draws=True):
    rs = np.random.RandomState(seed)
    t = np.arange(N) * Ts
    u_cmd = 0.8 * np.sin(2.0 * np.pi * 0.7 * t)
    x = np.zeros((2, N))
    y = np.zeros(N)
    y_true = np.zeros(N)
    bias = 0.0
    a_noise = 0.0
    P = np.zeros((2, 2))
    P_hist = np.zeros((N, 2, 2))
    Syy_hist = np.zeros(N)
    draws = np.zeros((N, 4))
    for k_idx in range(N - 1):
        d = rs.randn(4) if record_draws else None
        if record_draws:
            draws[k_idx] = d
        a_noise = rho_a * a_noise + np.sqrt(1.0 - rho_a**2) * sigma_a_ss * d[0]
        w_k = sigma_w * d[1]
        u_actual = u_cmd[k_idx] + a_noise
        x[:, k_idx + 1] = A @ x[:, k_idx] + (B[:, 0] * u_actual) + (G[:, 0] * w_k)
        bias = bias + sigma_bias_rw * np.sqrt(Ts) * d[2]
        v_k = sigma_v * d[3]
        y_analog = (C @ x[:, k_idx + 1])[0] + bias + v_k
        q_k = delta_q * np.round(y_analog / delta_q) - y_analog
        y[k_idx + 1] = y_analog + q_k
        y_true[k_idx + 1] = (C @ x[:, k_idx + 1])[0]
        P = A @ P @ A.T + G @ Qw @ G.T + B @ Qa @ B.T
        P_hist[k_idx + 1] = P
        Syy = C @ P @ C.T + Rv + Rq
        Syy_hist[k_idx + 1] = Syy[0, 0]
    return dict(u_cmd=u_cmd, x=x.T, y=y, y_true=y_true, P_hist=P_hist, Syy_hist=Syy_hist, draws=draws)


def seed_loop(N, seed=17):
    """The lesson's simulation loop alone (no recursion, no recording): the benchmark peer."""
    np.random.seed(seed)
    t = np.arange(N) * Ts
    u_cmd = 0.8 * np.sin(2.0 * np.pi * 0.7 * t)
    x = np.zeros((2, N))
    y = np.zeros(N)
    bias = 0.0
    a_noise = 0.0
    for k_idx in range(N - 1):
        a_noise = rho_a * a_noise + np.sqrt(1.0 - rho_a**2) * sigma_a_ss * np.random.randn()
        w_k = sigma_w * np.random.randn()
        u_actual = u_cmd[k_idx] + a_noise
        x[:, k_idx + 1] = (A @ x[:, k_idx] + (B[:, 0] * u_actual) + (G[:, 0] * w_k))
        bias = bias + sigma_bias_rw * np.sqrt(Ts) * np.random.randn()
        v_k = sigma_v * np.random.randn()
        y_analog = (C @ x[:, k_idx + 1])[0] + bias + v_k
        q_k = delta_q * np.round(y_analog / delta_q) - y_analog
        y[k_idx + 1] = y_analog + q_k
    return y


def seed_normals_layout(draws):
    """Map the lesson's draws (iteration k: a, w, bias, v, producing x_{k+1}, y_{k+1}) onto
    noiselab's per-sample normals (sample k: ar1, process, bias_walk for b_{k+1}, white for y_k):
    the sensor white draw of iteration k belongs to noiselab's sample k+1."""
    N = draws.shape[0]
    out = np.zeros((N, 4))
    out[:, 0:3] = draws[:, 0:3]
    out[1:, 3] = draws[:-1, 3]
    return out
