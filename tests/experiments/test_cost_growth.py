"""experiments.cost_growth at toy sizes: each measurement reports its cost and memory, and the ratios
set each row against its axis's reference and the work it does."""

from __future__ import annotations

import pytest

from experiments import cost_growth as C
from experiments import gpu_check as G
from experiments.common import bench_cloud
from ne_jax.train.run import INIT_CAPACITY_HEADROOM


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    """The ``--quick`` axes, their two 16 and 24 px scenes and the toy run."""
    a = C.axes(quick=True)
    root = tmp_path_factory.mktemp("cost_growth_scenes")
    scenes = [G.scene_dir(p, root, log=lambda m: None) for p in a.images]
    return a, scenes, G.presets(G.sizes(True))["default"]


def test_a_step_and_the_pool_it_draws_from(toy):
    a, scenes, run = toy
    pool, info = C.pool_cost(run, scenes[0], repeats=1)
    assert info["pixels"] == 8 * 16 * 16 and 0 < info["foreground"] < info["pixels"]
    assert info["device_bytes"] >= 16 * info["foreground"]  # an index and an RGB target per foreground pixel
    points = bench_cloud(a.clouds[0], run.render.shading.feature_dim, INIT_CAPACITY_HEADROOM)
    compiled = {}
    first = C.step_cost(run, points, pool, steps=1, repeats=1, compiled=compiled)
    again = C.step_cost(run, points, pool, steps=1, repeats=1, compiled=compiled)
    assert first["ms"] > 0 and first["program_mib"] > 0 and first["segments_lost"] >= 0
    assert len(compiled) == 1 and again["program_mib"] == first["program_mib"]  # the second compiled nothing


def test_a_render_and_a_round(toy):
    a, scenes, run = toy
    import jax

    from ne_jax.data.nerf_synthetic import load_split
    from ne_jax.pointcloud.init import Views
    from ne_jax.train.state import init_train_state

    points = bench_cloud(a.clouds[0], run.render.shading.feature_dim, INIT_CAPACITY_HEADROOM)
    params = init_train_state(run.train, run.render, points, jax.random.key(1), total_steps=run.total_steps).params
    r = C.render_cost(run, params, points, scenes[0], repeats=1)
    assert r["px"] == 16 and r["rays"] == 16 * 16 * run.render.pixel_samples ** 2 and r["rays_per_s"] > 0
    pool, _ = C.pool_cost(run, scenes[0], repeats=1)
    views = Views.from_split(load_split(scenes[0], "train"))
    rnd = C.round_cost(run, params, points, pool, views, a.grow_rays)
    stages = ("grow_s", "prune_s", "denoise_s", "normals_s")
    assert rnd["round_s"] == pytest.approx(sum(rnd[k] for k in stages), abs=0.02)
    assert rnd["tree_build_s"] >= 0 and rnd["tree_depth"] >= 1


def _row(axis, value, what, cost, **more):
    return {"axis": axis, "value": value, "what": what, C.COST[what]: cost, **more}


def test_ratios_against_each_axis_reference_and_its_work():
    a = C.axes(quick=False)
    stages = {k: 1.0 for k in ("grow_s", "prune_s", "denoise_s", "normals_s", "tree_build_s")}
    rows = C.with_ratios([
        _row("image", 200, "pool", 100), _row("image", 800, "pool", 1600),
        _row("image", 200, "step", 10.0), _row("image", 800, "step", 10.0),
        _row("batch", 1024, "step", 5.0), _row("batch", 2048, "step", 10.0), _row("batch", 8192, "step", 50.0),
        _row("cloud", 100_000, "step", 12.0), _row("cloud", 1_000_000, "step", 18.0),
        _row("depth", 17, "step", 10.0), _row("depth", 21, "step", 20.0),
        _row("render", 200, "render", 100.0), _row("render", 800, "render", 1600.0),
        _row("round", 100_000, "round", 2.0, **stages),
        _row("round", 1_000_000, "round", 40.0, **{**stages, "denoise_s": 30.0})], a)
    got = {(r["axis"], r["value"], r["what"]): (r["ratio"], r["work"], r["growth"]) for r in rows}
    assert got["image", 800, "pool"] == (16.0, 16.0, 1.0)  # bytes with the pixels
    assert got["image", 800, "step"] == (1.0, 1.0, 1.0)  # a step's rays do not change with the images
    assert got["batch", 1024, "step"] == (0.5, 0.5, 1.0) and got["batch", 8192, "step"] == (5.0, 4.0, 1.25)
    assert got["cloud", 1_000_000, "step"] == (1.5, 1.0, 1.5)  # a step's rays do not change with the cloud
    assert got["depth", 21, "step"] == (2.0, round(21 / 17, 3), round(2.0 / round(21 / 17, 3), 3))
    assert got["render", 800, "render"] == (16.0, 16.0, 1.0)
    assert got["round", 1_000_000, "round"] == (20.0, 10.0, 2.0)
    big = next(r for r in rows if r["axis"] == "round" and r["value"] == 1_000_000)
    assert big["denoise_ratio"] == 30.0 and big["grow_ratio"] == 1.0


@pytest.mark.slow
def test_the_quick_study_writes_its_results(tmp_path):
    import json

    assert C.main(["--quick", "--steps", "1", "--repeats", "1", "--render-repeats", "1", "--scene-root",
                   str(tmp_path / "scenes"), "--out-dir", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "cost_growth_quick.json").read_text())
    assert res["command"].startswith("python -m experiments.cost_growth --quick") and res["commit"]
    assert {r["axis"] for r in res["rows"]} == {"image", "batch", "cloud", "depth", "render", "round"}
    assert "| axis |" in (tmp_path / "cost_growth_quick.md").read_text()
