"""Capacities, Lost and the one growth rule: each buffer grows only when it lost something, by
powers of two, and a complete call changes nothing."""

import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.geometry.capacity import PACKING_STEP, Capacities, Lost, LostCounts, fit_packing, grow


def lost(frontier=0, slots=0, packing=0, emitted=(1, 2, 3)):
    """A :class:`Lost` of three rays: the given totals on the first ray, ``emitted`` per ray."""
    def first(v):
        return jnp.asarray([v, 0, 0], jnp.int32)

    return Lost(frontier=first(frontier), slots=first(slots), packing=first(packing),
                emitted=jnp.asarray(emitted, jnp.int32))


def test_nothing_lost_grows_nothing():
    assert grow(Capacities(), lost()) is None
    assert grow(Capacities(), Lost.none((4, 5))) is None
    assert Lost.none((4, 5)).counts() == LostCounts(rays=20)


def test_each_buffer_grows_only_on_its_own_loss():
    cap = Capacities(frontier=16, max_segments=8, segments_per_ray=2.0)
    assert grow(cap, lost(frontier=3)) == cap.replace(frontier=32)
    # slots: the next power of two that holds the most any ray found, at least twice as many
    assert grow(cap, lost(slots=1, emitted=(9, 2, 3))) == cap.replace(max_segments=16)
    assert grow(cap, lost(slots=1, emitted=(40, 2, 3))) == cap.replace(max_segments=64)
    # packing: times the power of two (at least 2) that holds the mean found per ray
    assert grow(cap, lost(packing=1, emitted=(3, 2, 1))) == cap.replace(segments_per_ray=4.0)
    assert grow(cap, lost(packing=5, emitted=(30, 20, 10))) == cap.replace(segments_per_ray=2.0 * 16)
    both = grow(cap, lost(frontier=1, packing=1, emitted=(3, 2, 1)))
    assert both == cap.replace(frontier=32, segments_per_ray=4.0)


def test_a_two_pass_walk_retries_more_rays_before_it_widens():
    cap = Capacities(frontier=64, first_pass_frontier=16, retry_share=0.25)
    once = grow(cap, lost(frontier=1))
    assert once == cap.replace(retry_share=0.5)
    twice = grow(once, lost(frontier=1))
    assert twice == cap.replace(retry_share=1.0)
    assert grow(twice, lost(frontier=1)) == twice.replace(frontier=128)


def test_unpacked_renders_never_grow_a_budget():
    cap = Capacities(segments_per_ray=None)
    assert grow(cap, lost(packing=4)) is None  # nothing to grow: packing is off
    assert fit_packing(cap, 100.0) == cap


def test_fit_packing_takes_the_smallest_step_that_holds_the_probe_and_never_lowers():
    assert PACKING_STEP == 2.0
    cap = Capacities(segments_per_ray=4.0)
    assert fit_packing(cap, 2.0) == cap
    assert fit_packing(cap, 3.2) == cap  # 1.25 x 3.2 = 4: held exactly
    assert fit_packing(cap, 4.0) == cap.replace(segments_per_ray=6.0)  # headroom 1.25: 5 -> 6
    assert fit_packing(cap, 6.9) == cap.replace(segments_per_ray=10.0)  # 8.6 -> 10, not 16
    assert fit_packing(cap, 13.0, headroom=1.0) == cap.replace(segments_per_ray=14.0)
    assert fit_packing(Capacities(segments_per_ray=16.0), 6.9) == Capacities(segments_per_ray=16.0)


def test_lost_counts_add_over_batches():
    a = lost(frontier=2, emitted=(1, 2, 3)).counts()
    b = lost(slots=1, packing=4, emitted=(7, 0, 0)).counts()
    total = a + b
    assert total == LostCounts(frontier=2, slots=1, packing=4, max_emitted=7, emitted=13, rays=6)
    assert total.total == 7 and total.as_dict()["max_emitted"] == 7
    assert grow(Capacities(segments_per_ray=2.0), total).segments_per_ray == 4.0
    np.testing.assert_array_equal(np.asarray(lost(frontier=2, slots=1, packing=4).count), [7, 0, 0])


@pytest.mark.parametrize("kwargs, match", [
    (dict(frontier=1), r"Capacities.frontier: expected an integer >= 2, found 1"),
    (dict(first_pass_frontier=64), r"Capacities.first_pass_frontier: expected None or an integer in .* = "
                                   r"\[2, 64\), found 64"),
    (dict(retry_share=0.0), r"Capacities.retry_share: expected a share in \(0, 1\], found 0.0"),
    (dict(max_segments=0), r"Capacities.max_segments: expected an integer >= 1, found 0"),
    (dict(segments_per_ray=0.0), r"Capacities.segments_per_ray: expected None or > 0, found 0.0"),
])
def test_bad_capacities_name_the_field(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Capacities(**kwargs)


def test_capacities_are_static_and_hashable():
    assert hash(Capacities(max_segments=64)) == hash(Capacities(max_segments=64))
    assert Capacities().segment_budget(10) == 40 and Capacities(segments_per_ray=None).segment_budget(10) is None
