"""ne_jax.memo: results kept by the bytes of the arrays they were computed from."""

from __future__ import annotations

import numpy as np
import pytest

from ne_jax.memo import LastResults, array_key


def test_equal_arrays_share_a_key_and_any_difference_does_not():
    a = np.arange(12.0).reshape(4, 3)
    assert array_key(a, 3) == array_key(a.copy(), 3)
    b = a.copy()
    b[2, 1] = np.nextafter(b[2, 1], np.inf)  # one ulp
    assert array_key(b, 3) != array_key(a, 3)
    assert array_key(a.astype(np.float32), 3) != array_key(a, 3)  # dtype
    assert array_key(a.reshape(3, 4), 3) != array_key(a, 3)  # shape
    assert array_key(a, 4) != array_key(a, 3)
    assert array_key(a[:, ::2]) == array_key(np.ascontiguousarray(a[:, ::2]))  # views by their values


def test_last_results_computes_once_per_key_and_keeps_the_last_ones():
    calls = []
    memo = LastResults(2)

    def compute(v):
        calls.append(v)
        return np.full(3, v), v

    for v in (1, 1, 2, 1, 3, 1, 2):
        out, tag = memo.get(("k", v), lambda v=v: compute(v))
        assert tag == v and (out == v).all()
    # 1 and 2 computed once each while kept; 3 pushed 2 out, so 2 is computed again
    assert calls == [1, 2, 3, 2]
    with pytest.raises(ValueError, match="read-only"):
        out[0] = 5
