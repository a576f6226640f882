"""The benchmark's part edits select the part, also on a cloud that spreads off the surface as a
trained one does: a region that reaches a neighbouring surface edits that surface too (a deletion
then leaves holes the ground truth does not have)."""

import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.benchmark.scenes import SCENES, get_scene, surface_samples

SPREAD = 0.02
"""Half-width of the jitter along the normal: the spread of a `tiny` model's wall points about the
surface (cup: 5th to 95th percentile of the radius within 0.025 of the wall)."""


def _selected(edit, xyz):
    p = jnp.asarray(xyz, jnp.float32)
    if edit.delete is not None:
        return np.asarray(edit.delete(p))
    return np.asarray(jnp.abs(edit.move(p) - p).max(axis=1) > 1e-6)


@pytest.mark.parametrize("name", sorted(SCENES))
def test_part_regions_keep_to_their_part_on_a_spread_cloud(name):
    scene = get_scene(name, 0.5)
    samples = surface_samples(scene, 20_000, seed=0)
    rng = np.random.default_rng(1)
    spread = samples["xyz"] + rng.uniform(-SPREAD, SPREAD, (len(samples["xyz"]), 1)) * samples["normal"]
    parts = {n: e for n, e in scene.edits.items() if e.kind in ("delete", "rigid")}
    assert parts, f"scene {name} has no part edit"
    for edit_name, edit in parts.items():
        on_surface = _selected(edit, samples["xyz"]).mean()
        off_surface = _selected(edit, spread).mean()
        assert on_surface > 0.005, (edit_name, on_surface)
        assert abs(off_surface - on_surface) < 0.25 * on_surface, (edit_name, on_surface, off_surface)
