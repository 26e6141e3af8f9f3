"""GICP's linearisation (``sparse._linearise``) with its Jacobian written out must give the
bits of the 3 x 6 matrix products it replaced (issue #21 item 5, speed only)."""

from __future__ import annotations

import numpy as np

from v2xlake.tasks.geometry import so3_exp
from v2xlake.tasks.register.backends import PLANE_EPS
from v2xlake.tasks.register.sparse import _linearise


def _reference(tp: np.ndarray, tn: np.ndarray, tr: np.ndarray, sp: np.ndarray,
               sn: np.ndarray, sr: np.ndarray, nn: np.ndarray, nn_d2: np.ndarray,
               T: np.ndarray, max_d2: float) -> tuple[np.ndarray, np.ndarray, int]:
    """The linearisation as written before: J = [[q]x, -I], W J and J^T W J as 3 x 6
    products, each sum taken left to right (Python floats: the same IEEE operations)."""
    H = [[0.0] * 6 for _ in range(6)]
    b = [0.0] * 6
    k = 1.0 - PLANE_EPS
    used = 0
    Tl = T.tolist()
    for i in range(len(sp)):
        j = int(nn[i])
        if j < 0 or not nn_d2[i] <= max_d2:
            continue
        p = sp[i].tolist()
        qx, qy, qz = (Tl[r][0] * p[0] + Tl[r][1] * p[1] + Tl[r][2] * p[2] + Tl[r][3]
                      for r in range(3))
        c = [2.0, 0.0, 0.0, 2.0, 0.0, 2.0]
        normals = []
        if tr[j] == tr[j]:
            normals.append(tn[j].tolist())
        if sr[i] == sr[i]:
            m = sn[i].tolist()
            normals.append([Tl[r][0] * m[0] + Tl[r][1] * m[1] + Tl[r][2] * m[2]
                            for r in range(3)])
        for n0, n1, n2 in normals:
            c[0] -= k * n0 * n0
            c[1] -= k * n0 * n1
            c[2] -= k * n0 * n2
            c[3] -= k * n1 * n1
            c[4] -= k * n1 * n2
            c[5] -= k * n2 * n2
        c00, c01, c02, c11, c12, c22 = c
        i00 = c11 * c22 - c12 * c12
        i01 = c02 * c12 - c01 * c22
        i02 = c01 * c12 - c02 * c11
        det = c00 * i00 + c01 * i01 + c02 * i02
        if not det > 1e-12:
            continue
        inv = 1.0 / det
        W = [[i00 * inv, i01 * inv, i02 * inv],
             [i01 * inv, (c00 * c22 - c02 * c02) * inv, (c01 * c02 - c00 * c12) * inv],
             [i02 * inv, (c01 * c02 - c00 * c12) * inv, (c00 * c11 - c01 * c01) * inv]]
        t = tp[j].tolist()
        r = [t[0] - qx, t[1] - qy, t[2] - qz]
        J = [[0.0, -qz, qy, -1.0, 0.0, 0.0],
             [qz, 0.0, -qx, 0.0, -1.0, 0.0],
             [-qy, qx, 0.0, 0.0, 0.0, -1.0]]
        WJ = [[W[a][0] * J[0][col] + W[a][1] * J[1][col] + W[a][2] * J[2][col]
               for col in range(6)] for a in range(3)]
        for a in range(6):
            b[a] += WJ[0][a] * r[0] + WJ[1][a] * r[1] + WJ[2][a] * r[2]
            for col in range(a, 6):
                H[a][col] += J[0][a] * WJ[0][col] + J[1][a] * WJ[1][col] + J[2][a] * WJ[2][col]
        used += 1
    out = np.array(H)
    for a in range(6):
        for col in range(a):
            out[a, col] = out[col, a]
    return out, np.array(b), used


def test_linearise_gives_the_bits_of_the_matrix_products() -> None:
    rng = np.random.default_rng(7)
    n_t, n_s = 400, 600
    tp = rng.normal(0, 20, (n_t, 3))
    tn = rng.normal(size=(n_t, 3))
    tn /= np.linalg.norm(tn, axis=1, keepdims=True)
    tr = rng.uniform(0, 1, n_t)
    tr[rng.uniform(size=n_t) < 0.2] = np.nan  # no surface: point to point
    sp = rng.normal(0, 20, (n_s, 3))
    sn = rng.normal(size=(n_s, 3))
    sn /= np.linalg.norm(sn, axis=1, keepdims=True)
    sr = rng.uniform(0, 1, n_s)
    sr[rng.uniform(size=n_s) < 0.2] = np.nan
    nn = rng.integers(-1, n_t, n_s)
    nn_d2 = rng.uniform(0, 1.5, n_s)
    sn[:50] = tn[nn[:50]]  # the same plane on both sides: a nearly singular covariance
    for seed in range(3):
        T = np.eye(4)
        T[:3, :3] = so3_exp(np.random.default_rng(seed).normal(0, 0.3, 3))
        T[:3, 3] = np.random.default_rng(seed + 10).normal(0, 5, 3)
        H, b, used = _linearise(tp, tn, tr, sp, sn, sr, nn, nn_d2, T, 1.0)
        H0, b0, used0 = _reference(tp, tn, tr, sp, sn, sr, nn, nn_d2, T, 1.0)
        assert used == used0 and used > 100
        assert H.tobytes() == H0.tobytes() and b.tobytes() == b0.tobytes()
