"""float64 numpy reference of the IST: the polar factor of the frame map ``A B^-1`` (loops, SVD)."""

import numpy as np


def frame_map_polar(x0, n0, x1, n1, pair, good=None):
    """``[C, 3, 3]``: for each slot ``j`` with neighbours ``pair[j] = (a, b)``, the rotation nearest to
    ``[u_a, u_b, n] [v_a, v_b, s n']^-1`` (tangent offsets, handedness sign ``s``); identity where
    ``good`` is False."""
    good = np.ones(len(x0), bool) if good is None else np.asarray(good)
    out = np.tile(np.eye(3), (len(x0), 1, 1))
    for j in np.flatnonzero(good):
        a, b = pair[j]
        t = lambda d, n: d - (d @ n) * n  # noqa: E731
        ua, ub = t(x0[a] - x0[j], n0[j]), t(x0[b] - x0[j], n0[j])
        va, vb = t(x1[a] - x1[j], n1[j]), t(x1[b] - x1[j], n1[j])
        s = np.sign(np.cross(ua, ub) @ n0[j]) * np.sign(np.cross(va, vb) @ n1[j])
        m = np.column_stack([ua, ub, n0[j]]) @ np.linalg.inv(np.column_stack([va, vb, s * n1[j]]))
        u, _, vt = np.linalg.svd(m)
        out[j] = u @ vt
    return out
