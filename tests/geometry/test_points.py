"""PointState: the host constructor, padding and its error messages."""

import jax
import numpy as np
import pytest

from ne_jax.geometry import PointState


def test_from_numpy_pads_dead_slots():
    xyz = np.arange(12, dtype=np.float32).reshape(4, 3)
    st = PointState.from_numpy(xyz, capacity=7, feature_dim=5, key=jax.random.PRNGKey(0))
    assert st.capacity == 7 and st.feature_dim == 5
    assert st.xyz.shape == (7, 3) and st.feature.shape == (7, 5) and st.ist.shape == (7, 3, 3)
    np.testing.assert_array_equal(np.asarray(st.alive), [1, 1, 1, 1, 0, 0, 0])
    np.testing.assert_array_equal(np.asarray(st.xyz[:4]), xyz)
    assert np.all(np.asarray(st.xyz[4:]) == 0) and np.all(np.asarray(st.feature[4:]) == 0)
    np.testing.assert_allclose(np.asarray(st.confidence[:4]), 0.5, rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(st.ist), np.broadcast_to(np.eye(3), (7, 3, 3)))
    assert np.all(np.isfinite(np.asarray(st.feature)))
    assert float(np.abs(np.asarray(st.feature[:4])).max()) > 0


def test_delete_keeps_shapes_and_indices():
    st = PointState.from_numpy(np.zeros((5, 3)), capacity=8)
    st2 = st.delete(np.array([1, 3]))
    assert st2.capacity == 8
    np.testing.assert_array_equal(np.asarray(st2.alive), [1, 0, 1, 0, 1, 0, 0, 0])


def test_jit_roundtrip_is_a_pytree():
    st = PointState.from_numpy(np.ones((3, 3)), capacity=4, feature_dim=2)
    out = jax.jit(lambda s: s.replace(xyz=s.xyz * 2))(st)
    np.testing.assert_array_equal(np.asarray(out.xyz[:3]), 2 * np.ones((3, 3)))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(xyz=np.zeros((4, 2))), r"xyz: expected an array of shape \[N, 3\], found shape \(4, 2\)"),
        (dict(xyz=np.zeros(6)), r"xyz: expected an array of shape \[N, 3\], found shape \(6,\)"),
        (dict(xyz=np.array([[0, 0, 0], [np.nan, 1, 2.0]])), r"xyz: expected finite positions.*index 1"),
        (dict(xyz=np.zeros((4, 3)), capacity=3), r"capacity: expected an integer >= max\(N, 1\) = 4, found 3"),
        (dict(xyz=np.zeros((4, 3)), feature=np.zeros((3, 2))), r"feature: expected shape \[N=4, F\]"),
        (dict(xyz=np.zeros((2, 3)), normal=np.zeros((2, 2))), r"normal: expected shape \[N=2, 3\]"),
        (dict(xyz=np.zeros((2, 3)), confidence=1.0), r"confidence: expected a value in \(0, 1\)"),
        (dict(xyz=np.zeros((2, 3)), feature_dim=0), r"feature_dim: expected an integer >= 1"),
    ],
)
def test_from_numpy_errors_name_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PointState.from_numpy(**kwargs)
