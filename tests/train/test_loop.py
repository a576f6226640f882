"""The training run (epochs, point-cloud rounds, checkpoints, resume) and the point-cloud
optimisation on a tiny generated scene, with the hard cases of issue 5: empty masks, one view,
growth past capacity, pruning everything, resuming another config."""

from __future__ import annotations

import dataclasses
import json
import shutil
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.benchmark.generate import generate_scene
from ne_jax.config_json import config_key
from ne_jax.data.nerf_synthetic import load_split
from ne_jax.pointcloud.rounds import (
    RoundConfig,
    add_points,
    prune_points,
    scan_growth,
    select_growth,
)
from ne_jax.render.renderer import PointScene
from ne_jax.train import CheckpointError, TrainConfig, loop, make_train_step, sample_batch
from ne_jax.train.loop import INFLIGHT_STEPS, TRAINING_GROWS, train
from ne_jax.train.model import load_trained
from ne_jax.train.sampler import build_pool

from tests.mini_presets import MINI_CAPS, TRAIN_SCENE, mini_run

RUN = mini_run(sampler=mini_run().sampler.replace(batch_size=126), capacities=MINI_CAPS.replace(segments_per_ray=8.0))
"""The module's run: :func:`mini_run` (3 epochs x 3 steps, rounds after epochs 1 and 2) on batches of
126 rays, which no 2 x 2 grid divides (the pixel-grid test trains on them), with a packing budget of 8
segments a ray from the start. A run that keeps its training config, batch and capacities, on a
cloud of the same capacity (every carving here keeps 1,500 points), reuses the training step
compiled for ``full_run``."""


def keeping_the_step(run):
    """``run`` with :data:`RUN`'s training config, its schedule included, whatever ``run``'s length:
    ``train`` then reuses the step compiled for ``full_run`` (the step compiles per training config)."""
    return run.replace(train=RUN.train)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    generate_scene("blocks", TRAIN_SCENE, root, seed=0, edits=())
    return root / "blocks"


@pytest.fixture(scope="module")
def full_run(scene_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "full"
    return train(RUN, scene_dir, out, progress=False, log=lambda s: None)


def _pool(result, run):
    scene_dir = json.loads((result.run_dir / "metrics.json").read_text())["scene_dir"]
    return build_pool(run.sampler, load_split(scene_dir, "train"), "white")


def _scan_rays(result):
    """``(pool, rays)``: the run's ray pool and a chunk of a round's growth scan from it
    (``rounds.grow_chunk`` rays, the shape the rounds of ``full_run`` compiled the scan for)."""
    pool = _pool(result, RUN)
    return pool, sample_batch(RUN.sampler.replace(batch_size=RUN.rounds.grow_chunk), pool, jax.random.key(1)).rays


def _same_state(a, b):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        x = jax.random.key_data(x) if jnp.issubdtype(x.dtype, jax.dtypes.prng_key) else x
        y = jax.random.key_data(y) if jnp.issubdtype(y.dtype, jax.dtypes.prng_key) else y
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_run_directory_history_and_no_recompile_within_an_epoch(full_run):
    run_dir = full_run.run_dir
    assert (run_dir / "config.json").is_file() and (run_dir / "checkpoints" / "latest").is_file()
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["initial_cloud"]["source"] == "carving" and not metrics["initial_cloud"]["ground_truth"]
    epochs = metrics["epochs"]
    assert [e["epoch"] for e in epochs] == [1, 2, 3] and epochs[-1]["step"] == 9
    assert int(full_run.state.step) == 9
    # rounds after epochs 1 and 2 (never after the last), each with every count reported
    assert "points" in epochs[0] and "points" in epochs[1] and "points" not in epochs[2]
    for e in epochs[:2]:
        p = e["points"]
        assert {"alive_before", "alive_after", "grown", "pruned", "denoised", "capacity"} <= set(p)
        assert p["alive_after"] == p["alive_before"] + p["grown"]["added"] - p["pruned"] - p["denoised"]
    # one compilation per shape: the first epoch compiles once; later ones only if the shapes changed
    assert epochs[0]["compiles"] == 1
    assert all(e["compiles"] <= 1 for e in epochs)
    for e in epochs:
        assert np.isfinite(e["loss/total"]) and e["skipped"] == 0


def test_resume_after_an_epoch_is_exact(full_run, scene_dir, tmp_path):
    out = tmp_path / "resumed"
    first = train(RUN, scene_dir, out, progress=False, log=lambda s: None, stop_after_epoch=1)
    assert int(first.state.step) == 3
    assert first.history[0]["compiles"] == 0  # the step compiled for full_run is reused in this process
    second = train(RUN, scene_dir, out, progress=False, log=lambda s: None)
    assert [e["epoch"] for e in second.history] == [1, 2, 3]
    _same_state(second.state, full_run.state)
    np.testing.assert_array_equal(np.asarray(second.scene.points.xyz), np.asarray(full_run.scene.points.xyz))
    np.testing.assert_array_equal(np.asarray(second.scene.points.alive), np.asarray(full_run.scene.points.alive))
    # the recorded training time sums both sittings: the first's epoch and rounds are in the history
    h = second.history
    expected = second.initial["seconds"] + sum(e["train_seconds"] + e.get("points", {}).get("seconds", 0) for e in h)
    assert second.recorded_seconds == pytest.approx(expected)
    assert h[0]["train_seconds"] == first.history[0]["train_seconds"]
    # and so does its CPU time, over the same parts (each recorded, so a resumed run still has it)
    cpu = second.initial["cpu_seconds"] + sum(e["train_cpu_seconds"] + e.get("points", {}).get("cpu_seconds", 0)
                                              for e in h)
    assert second.recorded_cpu_seconds == pytest.approx(cpu) and all(e["train_cpu_seconds"] > 0 for e in h)
    assert h[0]["train_cpu_seconds"] == first.history[0]["train_cpu_seconds"]
    # a history recorded without CPU times (an older run directory) has none, rather than a part of it
    older = second.replace(history=[{k: v for k, v in e.items() if k != "train_cpu_seconds"} for e in h])
    assert older.recorded_cpu_seconds is None


def test_the_cached_step_is_one_per_run_length():
    """``train()`` shares jitted steps between runs of the same configs; a run of another length (a
    fine-tune) gets a step of its own schedule, not the first run's."""
    step = loop._train_step(RUN.train, RUN.train_render, total_steps=RUN.total_steps)
    assert loop._train_step(RUN.train, RUN.train_render, total_steps=RUN.total_steps) is step
    assert loop._train_step(RUN.train, RUN.train_render, total_steps=RUN.total_steps + 1) is not step


def test_resuming_a_run_of_another_config_names_the_fields(full_run, scene_dir):
    other = RUN.replace(train=TrainConfig(lr=1e-3))
    with pytest.raises(CheckpointError, match=r"train\.lr"):
        train(other, scene_dir, full_run.run_dir, progress=False, log=lambda s: None)


def test_a_restart_removes_the_earlier_runs_checkpoints(full_run, scene_dir, tmp_path):
    out = tmp_path / "again"
    shutil.copytree(full_run.run_dir, out)
    lines = []
    again = train(RUN, scene_dir, out, resume=False, progress=False, log=lines.append, stop_after_epoch=1)
    assert int(again.state.step) == 3 and [e["epoch"] for e in again.history] == [1]
    assert any("removed the earlier run's checkpoints" in line for line in lines)
    steps = sorted(p.name for p in (out / "checkpoints").iterdir() if p.is_dir())
    assert steps == ["ckpt_00000003"]  # none of the finished run's (steps 3, 6, 9) is left to mix in
    assert [e["epoch"] for e in json.loads((out / "metrics.json").read_text())["epochs"]] == [1]


def test_load_trained_gives_back_the_final_model(full_run, scene_dir):
    model = load_trained(full_run.run_dir)
    assert model.scene_dir == scene_dir.resolve()
    _same_state(model.state, full_run.state)
    assert model.scene.capacities == full_run.scene.capacities  # the sizes in use, saved with the checkpoint
    camera = load_split(scene_dir, "test").camera(0)
    np.testing.assert_array_equal(np.asarray(model.render_image(camera).rgb),
                                  np.asarray(full_run.render_image(camera).rgb))
    with pytest.raises(FileNotFoundError, match="training run directory"):
        load_trained(full_run.run_dir / "nope")


def test_training_counts_traversal_losses_and_saves_the_capacities(scene_dir, tmp_path):
    """Buffers too small for the scene (not a setting: the run's key is unchanged): the batches lose
    frontier nodes and segment slots, each epoch's record says how many and which capacities were in
    force, and the traversal is not grown in training (``TRAINING_GROWS``: only the packing
    budget); the model comes back with the capacities it ended with."""
    starved = RUN.replace(epochs=2, round_epochs=(1, 0), capacities=MINI_CAPS.replace(frontier=2, max_segments=2))
    assert config_key(starved) == config_key(RUN.replace(epochs=2, round_epochs=(1, 0)))
    model = train(starved, scene_dir, tmp_path / "starved", progress=False, log=lambda s: None)
    assert len(model.history) == 2
    for e in model.history:
        assert e["lost"]["frontier"] > 0 and e["lost"]["slots"] > 0 and e["lost"]["rays"] == 3 * RUN.sampler.batch_size
        assert e["capacities"]["frontier"] == 2 and e["capacities"]["max_segments"] == 2
    assert TRAINING_GROWS == ("packing",)
    assert load_trained(model.run_dir).scene.capacities == model.scene.capacities


def test_empty_masks_fail_before_anything_is_written(scene_dir, tmp_path):
    split = load_split(scene_dir, "train")
    empty = dataclasses.replace(split, images=np.zeros_like(split.images))
    with pytest.raises(ValueError, match="no foreground"):
        train(RUN, scene_dir, tmp_path / "run", split=empty, progress=False, log=lambda s: None)
    assert not (tmp_path / "run").exists()


def test_a_scene_with_one_view_trains(scene_dir, tmp_path):
    split = load_split(scene_dir, "train")
    one = dataclasses.replace(split, images=split.images[:1], c2w=split.c2w[:1], file_paths=split.file_paths[:1],
                              image_paths=split.image_paths[:1])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = train(RUN.replace(round_epochs=(1, 0)), scene_dir, tmp_path / "one", split=one, progress=False,
                    log=lambda s: None, stop_after_epoch=1)
    assert any("min_views" in str(w.message) for w in caught)
    assert int(res.state.step) == 3 and np.isfinite(res.history[-1]["loss/total"])


def test_training_batches_take_the_samplers_grid_and_images_the_renders(scene_dir, tmp_path):
    """``sampler.pixel_samples = 1`` under a render grid of 2: the batches hold single rays (126 rays,
    which no 2 x 2 grid divides, train), and the model trains as the one-ray config does (an epoch of
    3 steps each)."""
    one = RUN.replace(round_epochs=(1, 0))
    grid = one.replace(render=one.render.replace(pixel_samples=2), sampler=one.sampler.replace(pixel_samples=1))
    assert one.sampler.batch_size == 126
    assert grid.train_render == one.render and one.train_render == one.render
    two = one.replace(sampler=one.sampler.replace(pixel_samples=2))  # the batches' grid is the sampler's alone
    assert two.train_render.pixel_samples == 2 and two.render.pixel_samples == 1
    runs = [train(r, scene_dir, tmp_path / name, progress=False, log=lambda s: None, stop_after_epoch=1)
            for name, r in (("one", one), ("grid", grid))]
    assert [int(r.state.step) for r in runs] == [3, 3]
    for a, b in zip(jax.tree_util.tree_leaves(runs[0].state.params), jax.tree_util.tree_leaves(runs[1].state.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError, match="SamplerConfig.pixel_samples"):
        one.sampler.replace(pixel_samples=0)


def test_the_host_waits_for_every_inflight_steps_th_step(scene_dir, tmp_path, monkeypatch):
    """No more than INFLIGHT_STEPS steps are queued ahead of the host (the XLA:CPU deadlock of
    docs/devices.md needs about 32 per device): the loop waits for steps 8, 16, ... of each run."""
    waited = []
    real = jax.block_until_ready
    monkeypatch.setattr(loop.jax, "block_until_ready", lambda x: waited.append(x) or real(x))
    steps = 2 * INFLIGHT_STEPS + 3
    run = keeping_the_step(RUN.replace(epochs=1, steps_per_epoch=steps, round_epochs=(1, 0)))
    res = train(run, scene_dir, tmp_path / "r", progress=False, log=lambda s: None, log_every=1000)
    assert int(res.state.step) == steps
    assert len(waited) == steps // INFLIGHT_STEPS and all(np.ndim(w) == 0 for w in waited)  # the step's loss


# ---------------------------------------------------------------- point-cloud rounds


def test_growth_past_capacity_reallocates_and_the_step_runs_on_the_new_shapes(full_run):
    run = RUN
    points = full_run.scene.points
    free = int(points.capacity - np.asarray(points.alive).sum())
    n = free + 50
    rng = np.random.default_rng(0)
    new_xyz = rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32)
    grown, slots = add_points(points, new_xyz, np.zeros((n, points.feature_dim), np.float32), headroom=1.25)
    alive_now = int(np.asarray(grown.alive).sum())
    assert grown.capacity == int(np.ceil((alive_now) * 1.25)) and alive_now == int(np.asarray(points.alive).sum()) + n
    np.testing.assert_allclose(np.asarray(grown.xyz)[slots], new_xyz)
    np.testing.assert_allclose(np.asarray(grown.confidence)[slots], 0.5, atol=1e-6)
    # old points keep their slots and values
    np.testing.assert_array_equal(np.asarray(grown.xyz)[:points.capacity][np.asarray(points.alive)],
                                  np.asarray(points.xyz)[np.asarray(points.alive)])
    state = full_run.state.with_points(grown, slots)
    mu = state.opt_state[0].mu["points"]["feature"]
    assert mu.shape[0] == grown.capacity and not np.asarray(mu)[slots].any()
    scene = PointScene.build(grown, run.render)
    pool = _pool(full_run, run)
    step = make_train_step(run.train, run.render, total_steps=run.total_steps)
    new_state, m = step(state, scene, sample_batch(run.sampler, pool, jax.random.key(0)))
    assert bool(m["ok"]) and int(new_state.step) == int(state.step) + 1


def test_pruning_everything_is_refused_and_reported(full_run):
    points = full_run.scene.points
    doomed = points.replace(conf_logit=jnp.full_like(points.conf_logit, -10.0))  # every confidence ~ 4.5e-5
    kept, report = prune_points(RoundConfig(), doomed)
    assert report["pruned_skipped"] and report["pruned"] == 0 and "min_points" in report["pruned_note"]
    np.testing.assert_array_equal(np.asarray(kept.alive), np.asarray(points.alive))
    some = points.replace(conf_logit=points.conf_logit.at[:10].set(-10.0))
    pruned, report = prune_points(RoundConfig(), some)
    assert report["pruned"] == int(np.asarray(points.alive)[:10].sum()) and not np.asarray(pruned.alive)[:10].any()


def test_select_growth_keeps_one_per_cell_by_priority():
    xyz = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [1.5, 0.1, 0.1], [0.3, 0.1, 0.2], [2.5, 0, 0]])
    prio = np.array([1.0, 3.0, 2.0, 0.5, 0.1])
    np.testing.assert_array_equal(select_growth(xyz, prio, cell=1.0, max_new=10), [1, 2, 4])
    np.testing.assert_array_equal(select_growth(xyz, prio, cell=1.0, max_new=2), [1, 2])
    assert select_growth(xyz[:0], prio[:0], 1.0, 5).size == 0


def test_scan_growth_candidates_lie_in_gaps_and_are_finite(full_run):
    run = RUN
    pool, rays = _scan_rays(full_run)
    scene = full_run.scene
    scan = jax.device_get(scan_growth(run.render, full_run.state.params, scene, rays, pool.background, 1.0, 0.0))
    for k in ("xyz", "feature", "sigma", "error"):
        assert np.isfinite(scan[k]).all(), k
    found = scan["found"]
    assert found.any()
    alive = np.asarray(scene.points.xyz)[np.asarray(scene.points.alive)]
    nearest = np.min(np.linalg.norm(scan["xyz"][found][:, None] - alive[None], axis=-1), axis=1)
    # the KNN candidate sets give the nearest point of the voxel's set; the global nearest may be
    # closer only for points outside the set, which a voxel's 16-point set rarely misses
    assert np.mean(nearest >= 1.0 * float(scene.tree.spacing) * 0.999) >= 0.9


def test_scan_growth_runs_under_the_runtime_checks(full_run):
    """With ``checks`` on, the scan runs under checkify (a plain jit refuses the stage checks) and
    finds what it finds without them."""
    run = RUN
    pool, rays = _scan_rays(full_run)
    args = (full_run.state.params, full_run.scene, rays, pool.background, 1.0, 0.0)
    plain = jax.device_get(scan_growth(run.render, *args))
    checked_scan = jax.device_get(scan_growth(run.render.replace(checks=True), *args))
    np.testing.assert_array_equal(checked_scan["found"], plain["found"])
    np.testing.assert_allclose(checked_scan["xyz"], plain["xyz"], rtol=1e-5, atol=1e-6)
