"""Rays split over a device mesh: a sharded render and a sharded training step equal the
single-device ones, and repeated steps do not recompile.

These tests need several devices: ``bash run.sh test`` runs them as their own step with
``XLA_FLAGS=--xla_force_host_platform_device_count=4`` (``pytest -m multidevice tests/devices``);
in a one-device process they are deselected. The mesh-independent parts (the mesh helpers, the
distributed flags) run in the default suite. Device counts 2, 3 (odd) and 4 against one device.
"""

from __future__ import annotations

import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.cli import build_parser
from ne_jax.compiles import count_compiles
from ne_jax.devices import default_mesh, even_mesh, padded_size, ray_mesh
from ne_jax.render.driver import render_chunked
from ne_jax.train import TrainConfig, init_train_state, make_train_step
from ne_jax.train.sampler import Batch

from tests.hard_cases.render_scene import CFG, build, scene_inputs

multidevice = pytest.mark.multidevice


def test_mesh_helpers_and_their_errors():
    mesh = ray_mesh(1)
    assert mesh.axis_names == ("rays",) and mesh.devices.size == 1
    assert padded_size(10, mesh) == 10
    with pytest.raises(ValueError, match=r"ray_mesh: expected 1 to \d+ devices .* found num_devices=0"):
        ray_mesh(0)


def test_distributed_flags_are_parsed_and_checked():
    args = build_parser().parse_args(["--coordinator", "localhost:1234", "--num-processes", "2", "--process-id", "1",
                                      "export", "run", "--out", "x.ply"])
    assert (args.coordinator, args.num_processes, args.process_id) == ("localhost:1234", 2, 1)
    from ne_jax.devices import initialize_distributed

    with pytest.raises(ValueError, match="--coordinator: expected host:port"):
        initialize_distributed("localhost", 1, 0)
    with pytest.raises(ValueError, match="0 <= id < N, found 2 and 2"):
        initialize_distributed("localhost:1", 2, 2)


def test_one_process_distributed_run_initializes_jax(tmp_path):
    """``ne-jax --coordinator ... --num-processes 1 --process-id 0`` starts jax.distributed (a real
    coordination service on localhost) before the command runs."""
    code = ("import sys, jax; from ne_jax.cli import main; "
            "rc = main(['--coordinator', 'localhost:47613', '--num-processes', '1', '--process-id', '0', "
            "'export', sys.argv[1], '--out', sys.argv[2]]); "
            "print('processes', jax.process_count(), 'rc', rc)")
    proc = subprocess.run([sys.executable, "-c", code, str(tmp_path / "missing"), str(tmp_path / "x.ply")],
                          capture_output=True, text=True, timeout=120)
    assert "processes 1 rc 2" in proc.stdout, proc.stdout + proc.stderr
    assert "missing: expected a training run directory" in proc.stderr


@pytest.fixture(scope="module")
def scene_and_rays():
    return build(scene_inputs(0))


@multidevice
@pytest.mark.parametrize("devices, chunk", [(2, None), (3, 25), (4, None)])
def test_sharded_render_equals_single_device(scene_and_rays, devices, chunk, monkeypatch):
    """3 devices (odd): chunks of 25 rays padded to 27, 64 rays in three chunks, the last one padded.
    Every chunk's render is split over all the devices."""
    import ne_jax.render.driver as R

    params, scene, rays, bg = scene_and_rays
    one = render_chunked(CFG, params, scene, rays, bg, mesh=ray_mesh(1))
    cfg = CFG if chunk is None else CFG.replace(chunk=chunk)
    placed = []
    real = R._render_chunk_maybe_checked

    def spy(*args):
        out = real(*args)
        placed.append({d.id for d in out.rgb.devices()})
        return out

    monkeypatch.setattr(R, "_render_chunk_maybe_checked", spy)
    many = render_chunked(cfg, params, scene, rays, bg, mesh=ray_mesh(devices))
    assert placed and all(ids == set(range(devices)) for ids in placed), placed
    for a, b in zip(jax.tree_util.tree_leaves(one), jax.tree_util.tree_leaves(many)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-6)


@multidevice
def test_sharded_render_packs_each_devices_share(scene_and_rays):
    """A chunk whose first half is a ray with 6 segments and whose second half a ray with 2, packed
    at 8 segments per ray: each device packs its own share of the chunk, nothing lost (a budget
    sized for the chunk's mean, 4 per ray, would lose segments on the first device)."""
    params, scene, rays, bg = scene_and_rays
    scene = scene.replace(capacities=scene.capacities.replace(segments_per_ray=8.0))
    count = np.asarray(render_chunked(CFG, params, scene, rays, bg, mesh=ray_mesh(1)).num_segments)
    six, two = int(np.flatnonzero(count == 6)[0]), int(np.flatnonzero(count == 2)[0])
    rays = rays.take(jnp.asarray([six] * 32 + [two] * 32))
    one = render_chunked(CFG, params, scene, rays, bg, mesh=ray_mesh(1))
    many = render_chunked(CFG.replace(chunk=64), params, scene, rays, bg, mesh=ray_mesh(2))
    assert int(many.lost.count.sum()) == 0
    for a, b in zip(jax.tree_util.tree_leaves(one), jax.tree_util.tree_leaves(many)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-6)


def _batch(rays, bg):
    rng = np.random.default_rng(1)
    target = np.concatenate([rng.uniform(size=(rays.num_rays, 3)), np.ones((rays.num_rays, 1))], 1)
    return Batch(rays=rays.replace(target=jnp.asarray(target, rays.origin.dtype)),
                 pixel=jnp.arange(rays.num_rays, dtype=jnp.int32), in_band=jnp.zeros(rays.num_rays, bool),
                 background=jnp.asarray(bg))


@multidevice
def test_sharded_training_step_equals_single_device_and_compiles_once(scene_and_rays):
    params, scene, rays, bg = scene_and_rays
    tcfg = TrainConfig()
    state = init_train_state(tcfg, CFG, scene.points, jax.random.key(0), total_steps=10)
    state = state.replace(params=params, opt_state=tcfg.optimizer(10).init({"params": params, "points": state.points}))
    batch = _batch(rays, bg)
    one, many = (make_train_step(tcfg, CFG, ray_mesh(1), total_steps=10),
                 make_train_step(tcfg, CFG, ray_mesh(4), total_steps=10))
    compiles = []  # (one device, four devices) compilations of each step
    s1, s4 = state, state
    for _ in range(3):
        with count_compiles() as c1:
            s1, m1 = one(s1, scene, batch)
        with count_compiles() as c4:
            s4, m4 = many(s4, scene, batch)
        compiles.append((c1.count, c4.count))
        assert bool(m4["ok"])
        for k in m1:
            np.testing.assert_allclose(np.asarray(m4[k]), np.asarray(m1[k]), rtol=2e-5, atol=1e-6, err_msg=k)
    assert compiles[1][1] == 0 and compiles[2] == (0, 0)  # from the second one-device step on: no compilation at all
    for a, b in zip(jax.tree_util.tree_leaves((s1.params, s1.points)),
                    jax.tree_util.tree_leaves((s4.params, s4.points))):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-4, atol=1e-6)


@multidevice
def test_a_batch_that_does_not_split_over_the_mesh_trains_on_the_part_it_splits_over(scene_and_rays):
    """66 rays on the default mesh (4 devices): the step runs on 3 (odd), equal to one device."""
    params, scene, rays, bg = scene_and_rays
    mesh = default_mesh()
    assert mesh.devices.size == 4
    assert even_mesh(64, mesh) is mesh
    assert even_mesh(66, mesh).devices.size == 3 and even_mesh(67, mesh).devices.size == 1
    rays = jax.tree_util.tree_map(lambda a: jnp.concatenate([a, a[:2]]), rays)
    tcfg = TrainConfig()
    state = init_train_state(tcfg, CFG, scene.points, jax.random.key(0), total_steps=10)
    state = state.replace(params=params, opt_state=tcfg.optimizer(10).init({"params": params, "points": state.points}))
    batch = _batch(rays, bg)
    s1, m1 = make_train_step(tcfg, CFG, ray_mesh(1), total_steps=10)(state, scene, batch)
    step = make_train_step(tcfg, CFG, total_steps=10)
    with count_compiles() as compiled:
        s3, m3 = step(state, scene, batch)
    assert {d.id for d in jax.tree_util.tree_leaves(s3.params)[0].devices()} == {0, 1, 2}
    assert bool(m3["ok"]) and compiled.names.count("jit(step_fn)") == 1  # once (besides slicing the inputs into shards)
    for k in m1:
        np.testing.assert_allclose(np.asarray(m3[k]), np.asarray(m1[k]), rtol=2e-5, atol=1e-6, err_msg=k)
    leaves = jax.tree_util.tree_leaves
    for a, b in zip(leaves((s1.params, s1.points)), leaves((s3.params, s3.points))):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-4, atol=1e-6)
