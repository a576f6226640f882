"""Smoke test of ``python -m experiments.accuracy_vs_time --study numerics`` at reduced sizes: the output
files and their schema, and monotone sanity of the numbers (no claim about timings beyond > 0)."""

from __future__ import annotations

import dataclasses
import importlib
import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest


def _load(name: str = "accuracy_vs_time"):
    """The module ``experiments.<name>``."""
    return importlib.import_module(f"experiments.{name}")


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    avt = _load()
    out = tmp_path_factory.mktemp("accuracy_vs_time")
    assert avt.main(["--study", "numerics", "--quick", "--out-dir", str(out)]) == 0
    return avt, out, json.loads((out / "accuracy_vs_time.json").read_text())


def _finite_nonneg(xs):
    return all(isinstance(x, float) and math.isfinite(x) and x >= 0 for x in xs)


def test_files_and_schema(quick_run):
    avt, out, res = quick_run
    for name in ("accuracy_vs_time.json", "accuracy_vs_time_numerics.md", "accuracy_vs_time_quadrature.png",
                 "accuracy_vs_time_knn.png", "accuracy_vs_time_precision.png"):
        assert (out / name).stat().st_size > 0, name
    assert res["study"] == "numerics" and res["command"].endswith("--quick")
    assert {"quadrature", "knn", "precision", "wall_s", "machine", "discussion", "plots"} <= set(res)
    q = res["quadrature"]
    n_s = len(q["s_values"])
    assert set(q["rules"]) == {"hermite", "hermite_o4", "spline", "spline_natural", "trapezoid", "stochastic"}
    for rule, row in q["rules"].items():
        assert set(row["error"]) == set(avt.FIELDS)
        for kind, err in row["error"].items():
            central = avt.quadrature_error(q, rule, kind)
            assert len(central) == n_s and _finite_nonneg(central)
            assert _finite_nonneg(err["max_abs"]) and all(m >= c - 1e-15 for m, c in zip(err["max_abs"], central)
                                                         if rule != "stochastic")
        assert len(row["ms_per_1e5_segments"]) == n_s and all(t > 0 for t in row["ms_per_1e5_segments"])
    kn = res["knn"]
    assert kn["rows"] and kn["exact"]
    for r in kn["rows"]:
        assert 0.0 <= r["recall"] <= 1.0 and r["ms_per_1e6_samples"] > 0
        assert _finite_nonneg([r["diff_random_mean"], r["diff_random_max"], r["diff_smooth_mean"]])
    pr = res["precision"]
    for key in ("rgb_max_abs_diff", "rgb_mean_abs_diff", "opacity_max_abs_diff", "time_ratio_f64_over_f32"):
        assert math.isfinite(pr[key]) and pr[key] >= 0
    assert pr["lost_segments"] == [0, 0]
    md = (out / "accuracy_vs_time_numerics.md").read_text()
    assert "#### Quadrature" in md and "#### KNN" in md and "float64" in md and res["command"] in md


def test_quadrature_converges(quick_run):
    avt, _, res = quick_run
    q = res["quadrature"]
    s = q["s_values"]
    i4, i22 = s.index(4), s.index(22)
    for rule in ("hermite", "hermite_o4", "spline", "spline_natural", "trapezoid"):
        smooth = avt.quadrature_error(q, rule, "smooth")
        assert smooth[i22] < 0.1 * smooth[i4], rule  # more samples: much smaller error on a smooth field
        assert all(b <= a for a, b in itertools.pairwise(smooth)), (rule, smooth)  # never grows with s
        step = avt.quadrature_error(q, rule, "step")
        assert step[i22] < step[i4], rule
    order = {r: q["rules"][r]["order"]["smooth"] for r in q["rules"]}
    # Fitted orders (s >= 8 only: few points at quick sizes, hence the loose bounds).
    assert 1.7 < order["trapezoid"] < 2.3
    assert 2.6 < order["hermite"] < 3.4
    assert order["spline"] > 3.5 and order["hermite_o4"] > 3.3
    assert 0.8 < order["stochastic"] < 2.2
    stoch = avt.quadrature_error(q, "stochastic", "smooth")
    assert stoch[i22] < stoch[i4]


def test_knn_sanity(quick_run):
    _, _, res = quick_run
    kn = res["knn"]
    for k in {r["k"] for r in kn["rows"]}:
        rows = sorted((r for r in kn["rows"] if r["k"] == k), key=lambda r: r["candidates"])
        recall = [r["recall"] for r in rows]
        # a larger candidate set is a superset (nearest-first), so recall cannot drop
        assert all(b >= a - 1e-9 for a, b in itertools.pairwise(recall)), recall
        assert recall[-1] > 0.9
    for e in kn["exact"]:
        assert e["recall_vs_scipy"] > 0.999  # brute force agrees with scipy's exact KNN


def test_precision_sanity(quick_run):
    _, _, res = quick_run
    pr = res["precision"]
    assert pr["rgb_max_abs_diff"] < 1e-3  # float32 rendering is far below an 8-bit step
    assert pr["rgb_mean_abs_diff"] <= pr["rgb_max_abs_diff"]


def test_fit_order_recovers_a_power_law():
    avt = _load()
    s = np.array([4, 8, 16, 32, 64])
    assert avt.fit_order(s, 3.0 * (1.0 / (s - 1)) ** 3, "hermite") == pytest.approx(3.0)
    assert avt.fit_order(s, 0.5 * (1.0 / s) ** 1.5, "stochastic") == pytest.approx(1.5)


# ------------------------------------------------------------------------- --study image (part 2)


@pytest.fixture(scope="module")
def mini(tmp_path_factory):
    """``(root, scene_dir, run)``: a 24-px generated glossy scene (as tests/edit/test_model.py) with the
    ``bend`` edit the image study scores, and a RunConfig of a few steps."""
    from ne_jax.benchmark.generate import generate_scene

    from tests.mini_presets import mini_benchmark, short_run

    root = tmp_path_factory.mktemp("avt_mini")
    generate_scene("glossy", mini_benchmark(train_views=4), root / "bench", seed=0, edits=("bend",))
    return root, root / "bench" / "glossy", short_run()


@pytest.fixture(scope="module")
def short_model(mini):
    """The run directory of a model trained for a few steps on the mini scene."""
    from ne_jax.train.loop import train

    root, scene_dir, run = mini
    train(run, scene_dir, root / "short_model", progress=False, log=lambda s: None)
    return root / "short_model"


@pytest.fixture(scope="module")
def initial_model(mini, tmp_path_factory):
    """The run directory of the mini scene's model as a training run starts it (its initial cloud and
    colour model, no step), with one epoch's record in ``metrics.json``."""
    import jax

    from ne_jax.data.nerf_synthetic import load_split
    from ne_jax.pointcloud.init import Views
    from ne_jax.render.renderer import PointScene
    from ne_jax.train.loop import _keys, initial_cloud, initial_points
    from ne_jax.train.model import TrainedModel, save_trained
    from ne_jax.train.state import init_train_state

    _, scene_dir, run = mini
    views = Views.from_split(load_split(scene_dir, "train"))
    k_points, k_model, *_ = _keys(run.seed)  # train()'s keys
    points = initial_points(run, initial_cloud(run.init, scene_dir, views), views, k_points)
    init = jax.jit(init_train_state, static_argnums=(0, 1))  # one program, not flax's eager operations
    model = TrainedModel(run=run, state=init(run.train, run.render, points, k_model),
                         scene=PointScene.build(points, run.render, run.capacities), scene_dir=scene_dir)
    epochs = [{"epoch": 1, "psnr": 12.5, "train_seconds": 3.0}]
    return save_trained(model, tmp_path_factory.mktemp("initial_model") / "run", metrics={"epochs": epochs})


@pytest.fixture(scope="module")
def image_run(mini, short_model):
    """The image study in ``--quick`` mode on the short model and its zero-shot "bend" edit."""
    avt = _load()
    root, _, _ = mini
    out = root / "results"
    assert avt.main(["--study", "image", "--run", str(short_model), "--out-dir", str(out), "--test-views", "2",
                     "--timing-passes", "2", "--quick"]) == 0
    return out, json.loads((out / "accuracy_vs_time_image_test.json").read_text()), short_model


def test_image_study_needs_a_run(capsys):
    avt = _load()
    assert avt.main(["--study", "image"]) == 2
    assert "needs a trained model: pass --run RUN_DIR" in capsys.readouterr().err
    with pytest.raises(ValueError, match="test_views: expected at least 1 test view, found 0"):
        avt.main(["--study", "image", "--run", "no_such_run", "--test-views", "0"])


@pytest.mark.slow  # a study run end to end: -m slow
def test_image_study_files_and_schema(image_run):
    out, res, run_dir = image_run
    for name in ("accuracy_vs_time_image_test.json", "accuracy_vs_time_image_test.md",
                 "accuracy_vs_time_image_test.png"):
        assert (out / name).stat().st_size > 0, name
    assert res["study"] == "image" and res["command"].endswith("--test-views 2 --timing-passes 2 --quick")
    assert res["edit"] == "bend" and res["preset"] == "test"
    assert res["sizes"]["test_views"] == 2 and res["sizes"]["timing_passes"] == 2
    assert {"targets", "sizes", "machine", "discussion", "own_position", "wall_s", "preset"} <= set(res)
    assert [t["target"] for t in res["targets"]] == ["original", "edit"]
    views = min(2, len(json.loads((Path(res["scene_dir"]) / "transforms_test.json").read_text())["frames"]))
    assert all(t["split"].startswith(f"test ({views} views") for t in res["targets"])
    from ne_jax.train.run import load_run_config

    image = _load("accuracy_vs_time_image")
    own = load_run_config(run_dir).render
    for t in res["targets"]:
        rows = t["rows"]
        cfg = own.with_effects(ist=True) if t["target"] == "edit" else own
        expected = [s.label for s in image.settings_for(cfg, image.ImageSizes.quick())]
        assert [r["label"] for r in rows] == expected  # one row per setting, in order
        assert rows[0]["knob"] == "own" and {"samples", "points", "chunk"} <= {r["knob"] for r in rows}
        for r in rows:
            assert {"psnr", "ssim", "ms_per_image", "compile_s", "d_psnr", "time_ratio", "on_front",
                    "lost_segments", "alive_points", "overflow_rays"} <= set(r)
            assert 0 <= r["overflow_rays"] <= 40_000
            assert math.isfinite(r["psnr"]) and 0.0 < r["ssim"] <= 1.0
            assert math.isfinite(r["ms_per_image"]) and r["ms_per_image"] > 0 and r["compile_s"] >= 0
        # the front: non-empty, made of rows no other row beats
        assert t["front"] and all(rows[i]["on_front"] for i in t["front"])
        for i in t["front"]:
            assert not any(b["ms_per_image"] < rows[i]["ms_per_image"] and b["psnr"] > rows[i]["psnr"] for b in rows)
    md = (out / "accuracy_vs_time_image_test.md").read_text()
    assert "Pareto front" in md and "the own config (`test`)" in md and res["command"] in md


@pytest.mark.slow  # a study run end to end: -m slow
def test_image_study_summary_only_rewrites_the_presets_files(image_run, capsys):
    out, res, _ = image_run
    md = out / "accuracy_vs_time_image_test.md"
    md.write_text("stale")
    avt = _load()
    assert avt.main(["--study", "image", "--summary-only", "--preset", "test", "--out-dir", str(out)]) == 0
    assert "Pareto front" in md.read_text()
    with pytest.raises(FileNotFoundError, match="accuracy_vs_time_image_paper.json: no image study results"):
        avt.main(["--study", "image", "--summary-only", "--preset", "paper", "--out-dir", str(out)])


def test_evenly_spaced_views():
    _load()
    image = _load("accuracy_vs_time_image")
    assert image.evenly_spaced(20, 5) == [0, 5, 10, 14, 19]
    assert image.evenly_spaced(3, None) == image.evenly_spaced(3, 7) == [0, 1, 2]
    assert image.evenly_spaced(9, 1) == [0]
    with pytest.raises(ValueError, match="expected at least 1, found 0"):
        image.evenly_spaced(9, 0)


def test_image_frontier_settings_change_only_the_frontier():
    image = _load("accuracy_vs_time_image")
    from tests.mini_presets import tiny_caps, tiny_render

    own, caps = tiny_render(), tiny_caps()
    settings = image.settings_for(own, image.ImageSizes.full(), caps)
    rows = [s for s in settings if s.knob == "frontier"]
    assert [s.value for s in rows] == [4, 8]  # a quarter and a half of the tiny capacities' 16
    for s in rows:
        assert s.capacities == caps.replace(frontier=s.value)
        assert s.cfg == own
    # only the frontier and the presets change the capacities
    assert {s.knob for s in settings if s.capacities is not None} <= {"frontier", "preset"}
    # a two-pass own walk keeps its first pass where it is narrower than the scaled frontier
    two = caps.replace(frontier=64, first_pass_frontier=16)
    rows = [s for s in image.settings_for(own, image.ImageSizes.full(), two) if s.knob == "frontier"]
    assert [(s.capacities.frontier, s.capacities.first_pass_frontier) for s in rows] == [(16, None), (32, 16)]


@pytest.mark.slow  # a study run end to end: -m slow
def test_bench_traversal_two_pass_is_the_reference_bit_for_bit(image_run, tmp_path):
    """``python -m experiments.bench_traversal --quick`` on the smoke-test model: the two-pass walk gives the
    reference's segments, pixels and (after 2 training steps) parameters exactly."""
    bench = _load("bench_traversal")
    _, _, run_dir = image_run
    assert bench.main(["--run", str(run_dir), "--quick", "--out-dir", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "bench_traversal.json").read_text())
    ref, two = res["rows"]
    assert ref["walk_ratio"] == 1.0 and two["changes"]["first_pass_frontier"] < 16
    assert two["segments_equal_reference"] and two["max_abs_rgb_diff"] == 0.0
    assert two["max_abs_param_diff"] == 0.0 and two["train_segments_lost"] == ref["train_segments_lost"]
    assert "two passes" in (tmp_path / "bench_traversal.md").read_text()
    with pytest.raises(SystemExit, match="expected a trained run directory"):
        bench.main(["--run", str(tmp_path / "missing")])


@pytest.mark.slow  # a study run end to end: -m slow
def test_bench_presets_quick(image_run, tmp_path):
    """``python -m experiments.bench_presets --quick`` on the smoke-test model: one row per preset measured, the
    ratios against ``default``, the projection from the measured step, and clear refusals."""
    bench = _load("bench_presets")
    _, _, run_dir = image_run
    assert bench.main(["--run", str(run_dir), "--quick", "--out-dir", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "bench_presets_cpu.json").read_text())
    rows = {r["label"]: r for r in res["rows"]}
    assert list(rows) == ["tiny", "default"]
    assert rows["default"]["step_ratio"] == 1.0 and rows["default"]["frontier"] == [16, 64]
    assert (rows["tiny"]["batch_rays"], rows["default"]["batch_rays"]) == (1024, 2048)
    for r in rows.values():
        assert r["ms_per_step"] > 0 and r["ms_per_image"] > 0 and math.isfinite(r["psnr_view0"])
        assert r["projected_train_min"] == pytest.approx(r["total_steps"] * r["ms_per_step"] / 6e4, abs=0.06)
        assert r["train_segments_lost"] == r["lost_to_capacity"] + r["lost_to_budget"] >= 0
        assert 0 <= r["first_batch"]["rays_at_max_segments"] <= r["batch_rays"]
    assert "| tiny |" in (tmp_path / "bench_presets_cpu.md").read_text()
    with pytest.raises(SystemExit, match="expected a trained run directory"):
        bench.main(["--run", str(tmp_path / "missing")])
    with pytest.raises(SystemExit, match="--steps: expected at least 1, found 0"):
        bench.main(["--run", str(run_dir), "--steps", "0"])


def test_compare_runs_same_and_different(initial_model, tmp_path, capsys):
    """``python -m experiments.compare_runs``: a run against a copy of itself is equal bit for bit (exit 0); a
    copy whose checkpoint holds other parameters is not (exit 1). (What the runs trained does not matter:
    the run directory holds a model as training starts it.)"""
    import shutil

    compare = _load("compare_runs")
    run_dir = initial_model
    assert compare.main([str(run_dir), str(run_dir)]) == 0
    assert "every array equal bit for bit: True" in capsys.readouterr().out
    import jax

    from ne_jax.train.model import load_trained, save_trained

    model = load_trained(run_dir)
    nudge = jax.jit(lambda params: jax.tree_util.tree_map(lambda a: a + 1e-3, params))  # one program
    nudged = model.state.replace(params=nudge(model.state.params))
    other = tmp_path / "other"
    save_trained(dataclasses.replace(model, state=nudged), other)
    shutil.copy(run_dir / "metrics.json", other / "metrics.json")
    assert compare.main([str(run_dir), str(other)]) == 1
    out = capsys.readouterr().out
    assert "every array equal bit for bit: False" in out and "B / A = 1.000" in out


@pytest.mark.slow  # a study run end to end: -m slow
def test_image_study_sanity(image_run):
    _, res, _ = image_run
    for t in res["targets"]:
        rows = {r["label"]: r for r in t["rows"]}
        full, quarter = rows["points 100%"], rows["points 25%"]
        assert quarter["alive_points"] == pytest.approx(0.25 * full["alive_points"], abs=1)
        # deleting three points in four cannot make the images better (beyond noise)
        assert quarter["psnr"] <= full["psnr"] + 0.5, (t["target"], quarter["psnr"], full["psnr"])
        # the same render twice scores the same; a chunk size changes no pixel (its accuracy is the own config's)
        assert full.get("same_as") == "own config" and full["psnr"] == t["rows"][0]["psnr"]


# ---------------------------------------------------------------------- --study training (part 3)


def _training():
    _load()
    return _load("accuracy_vs_time_training")


def test_training_study_needs_a_scene(capsys):
    avt = _load()
    assert avt.main(["--study", "training"]) == 2
    assert "needs a scene to train on: pass --scene DIR" in capsys.readouterr().err
    assert avt.main(["--study", "training", "--preset", "huge", "--scene", "x"]) == 2
    assert "--preset: expected one of tiny, default, paper, found 'huge'" in capsys.readouterr().err


def test_training_study_cli_passes_finished_only(mini, tmp_path):
    """``--finished-only`` reaches the study: with no finished runs it refuses before training anything."""
    avt = _load()
    _, scene_dir, _ = mini
    with pytest.raises(FileNotFoundError, match="finished_only: the preset's own run .* has not finished"):
        avt.main(["--study", "training", "--scene", str(scene_dir), "--quick", "--runs", str(tmp_path / "runs"),
                  "--out-dir", str(tmp_path / "out"), "--finished-only"])
    assert not (tmp_path / "runs").exists() and not (tmp_path / "out").exists()


def test_training_candidates_change_one_knob():
    from ne_jax.train.run import RunConfig

    tr = _training()
    own = RunConfig.tiny()
    cands = tr.candidates_for(own)
    assert cands[0].label == "own" and cands[0].run == own
    keys = [tr.run_key(c.run) for c in cands]
    assert len(set(keys)) == len(keys)  # every candidate trains its own model, in its own run directory
    by = {c.label: c.run for c in cands}
    k_half = by[f"K={own.render.kdtree.knn_k // 2}"]
    assert k_half.replace(render=own.render) == own
    assert k_half.render.kdtree.replace(knn_k=own.render.kdtree.knn_k) == own.render.kdtree
    # 2K beyond the candidate set widens the set to 2K (the preset's K = 16 fills its 16 candidates)
    k, n = own.render.kdtree.knn_k, own.render.kdtree.num_candidates
    assert 2 * k > n
    for label in (f"K={2 * k} ({2 * k} candidates)", f"K={2 * k} ({2 * k} candidates), s x0.5"):
        assert by[label].render.kdtree.knn_k == 2 * k and by[label].render.kdtree.num_candidates == 2 * k
    narrow = own.replace(render=own.render.replace(kdtree=own.render.kdtree.replace(knn_k=4)))  # 2K fits: no widening
    labels = {c.label: c.run for c in tr.candidates_for(narrow)}
    assert {"K=8", "K=8, s x0.5", "K=8, s x0.5, steps x0.5"} <= set(labels)
    assert labels["K=8"].render.kdtree.replace(knn_k=4) == narrow.render.kdtree
    half = by["steps x0.5"]
    assert half.steps_per_epoch == own.steps_per_epoch // 2 and half.train.total_steps == half.total_steps
    assert by["own, seed 1"] == own.replace(seed=own.seed + 1)
    narrow = own.capacities.frontier // 4  # appended last, so earlier indices keep their runs
    assert cands[-2].label == f"frontier={narrow}" and cands[-2].run.replace(capacities=own.capacities) == own
    assert cands[-2].run.capacities == own.capacities.replace(frontier=narrow)
    assert cands[-1].knob == "two-pass" and cands[-1].run.replace(capacities=own.capacities) == own
    assert cands[-1].run.capacities.first_pass_frontier == narrow
    # they differ from the preset only in the buffer sizes: the same config key, another run directory
    for c in cands[-2:]:
        assert tr.config_key(c.run) == tr.config_key(own) and tr.run_key(c.run) != tr.run_key(own)


def test_short_candidates_for_hour_long_presets():
    from ne_jax.geometry.capacity import Capacities
    from ne_jax.geometry.kdtree import KDTreeConfig
    from ne_jax.render.quadrature import QuadratureConfig
    from ne_jax.train.run import RunConfig

    tr = _training()
    own = RunConfig.default()
    cands = tr.candidates_for(own, candidate_set="short")
    # the preset walks in two passes already (16 then 64): no two-pass candidate, and the narrow frontier
    # is walked in one pass
    assert own.capacities.first_pass_frontier == 16 and own.capacities.retry_share == tr.TWO_PASS_SHARE
    assert [c.knob for c in cands] == ["own", "seed", "k", "k", "steps", "paper", "paper", "candidates", "frontier"]
    paper, paper_short = cands[5].run, cands[6].run
    half = cands[7].run.render.kdtree
    assert (half.num_candidates, half.knn_k) == (16, 16) and cands[7].label == "16 candidates (K=16)"
    assert cands[7].run.replace(render=own.render) == own  # only the candidate set changes
    one_pass = own.capacities.replace(first_pass_frontier=None)
    assert cands[8].label == "frontier=16" and cands[8].run.capacities == one_pass.replace(frontier=16)
    assert cands[8].run.replace(capacities=own.capacities) == own
    # a preset that walks in one pass gets the two-pass walk of its full width as its last candidate
    single = own.replace(capacities=one_pass)
    again = tr.candidates_for(single, candidate_set="short")
    assert [c.knob for c in again][-2:] == ["frontier", "two-pass"]
    assert again[-1].run.capacities == own.capacities and again[-1].run.replace(capacities=one_pass) == single
    assert paper.render.kdtree == KDTreeConfig() and paper.render.quadrature == QuadratureConfig()
    # only the per-sample settings change; the walk is the one the paper's tree config had (one pass)
    assert paper.replace(render=own.render, capacities=own.capacities) == own
    assert paper.capacities == Capacities(segments_per_ray=own.capacities.segments_per_ray)
    assert paper_short.total_steps == own.total_steps // 4
    # a preset already at the paper's settings has no paper candidates
    at_paper = own.replace(render=paper.render)
    assert "paper" not in [c.knob for c in tr.candidates_for(at_paper, candidate_set="short")]
    with pytest.raises(ValueError, match="candidate_set: expected one of"):
        tr.candidates_for(own, candidate_set="most")


def _row(label, psnr, train_s, ms, knob="k"):
    return {"label": label, "knob": knob, "psnr": psnr, "train_s": train_s, "ms_per_image": ms, "ssim": 0.9,
            "final_points": 100}


def test_choose_preset_rule():
    tr = _training()
    own = _row("own", 22.0, 100, 100, "own")
    rows = [own, _row("seed", 21.8, 100, 100, "seed"), _row("better", 22.5, 110, 110),
            _row("best but slow", 23.0, 200, 100), _row("worse", 21.0, 120, 90)]
    ch = tr.choose_preset(rows)
    assert ch["label"] == "better" and ch["gain_db"] == pytest.approx(0.5) and not ch["confirmed"]
    assert ch["seed_noise_db"] == pytest.approx(0.2) and ch["best_affordable_db"] == 22.5
    assert 3 in ch["train_front"] and 4 not in ch["train_front"]  # "worse" is beaten by "own"
    # within the noise (0.6 dB) of the best affordable PSNR, the cheapest to train wins: the preset itself
    ch = tr.choose_preset([own, _row("seed", 21.4, 100, 100, "seed"), _row("better", 22.5, 110, 110)])
    assert ch["pick"] == 0 and ch["confirmed"]
    # as good within the noise for half the training time: that is the pick
    ch = tr.choose_preset([own, _row("seed", 21.8, 100, 100, "seed"), _row("short", 22.1, 50, 100, "steps")])
    assert ch["label"] == "short" and ch["train_ratio"] == pytest.approx(0.5) and not ch["confirmed"]
    # the seed row is the preset itself: cheaper by chance, it is never the pick
    ch = tr.choose_preset([own, _row("seed", 21.95, 97, 116, "seed"), _row("short", 21.3, 50, 90, "steps")])
    assert ch["pick"] == 0 and ch["confirmed"]
    # nothing better inside the budget
    ch = tr.choose_preset([own, _row("slow", 25.0, 130, 100), _row("slow image", 25.0, 100, 200)])
    assert ch["pick"] == 0 and ch["confirmed"]


@pytest.mark.slow  # a study run end to end: -m slow
def test_training_study_smoke_and_cache(mini):
    root, scene_dir, run = mini
    tr = _training()
    runs, out = root / "avt_training_runs", root / "avt_training"
    cands = tr.candidates_for(run, quick=True)
    labels = [c.label for c in cands]
    with pytest.raises(FileNotFoundError, match="finished_only: the preset's own run .* has not finished"):
        tr.run_training(scene_dir, runs, out, "cmd", quick=True, run=run, finished_only=True)
    # --train-only trains the candidates named and writes nothing else
    assert tr.run_training(scene_dir, runs, out, "cmd", quick=True, run=run, train_only=[0]) is None
    assert not out.exists()
    with pytest.raises(IndexError, match=r"train_only: expected candidate indices in 0..1, found \[5\]"):
        tr.run_training(scene_dir, runs, out, "cmd", quick=True, run=run, train_only=[5])
    # --finished-only scores what has trained and names the rest; it trains nothing
    part = tr.run_training(scene_dir, runs, out, "cmd", quick=True, run=run, finished_only=True)
    assert [r["label"] for r in part["rows"]] == labels[:1] and part["unfinished"] == labels[1:]
    assert not tr.is_finished(cands[1].run, runs)
    md = (out / f"accuracy_vs_time_training_test_{scene_dir.name}.md").read_text()
    assert f"left out of this interim result: {labels[1]}" in md
    summary = json.loads((out / "accuracy_vs_time_training_test.json").read_text())
    assert summary["unfinished"] == labels[1:]
    # one plain call trains the rest and scores all
    res = tr.run_training(scene_dir, runs, out, "cmd --quick", quick=True, run=run)
    stem = f"accuracy_vs_time_training_test_{scene_dir.name}"
    for name in (stem, "accuracy_vs_time_training_test"):  # the scene's study and the summary over scenes
        for ext in ("json", "md", "png"):
            assert (out / f"{name}.{ext}").stat().st_size > 0, (name, ext)
    rows = res["rows"]
    assert [r["label"] for r in rows] == labels and res["unfinished"] == []
    for r in rows:
        assert math.isfinite(r["psnr"]) and 0.0 < r["ssim"] <= 1.0 and r["train_s"] > 0 and r["ms_per_image"] > 0
        assert r["steps"] == run.total_steps
    assert [r["cached"] for r in rows] == [True, False]  # candidate 0 was trained by --train-only
    ch = res["choice"]
    assert ch["train_front"] and ch["render_front"] and 0 <= ch["pick"] < len(rows)
    assert [r["score_cached"] for r in rows] == [True, False]  # --finished-only scored candidate 0
    again = tr.run_training(scene_dir, runs, out, "cmd --quick", quick=True, run=run)  # cached: nothing trains
    assert all(r["cached"] and r["score_cached"] for r in again["rows"])
    assert [(r["psnr"], r["ssim"], r["train_s"]) for r in again["rows"]] == \
        [(r["psnr"], r["ssim"], r["train_s"]) for r in rows]
    # a kept score is evaluated again once what it depends on changes, and gives the same numbers
    kept_path = Path(rows[1]["run_dir"]) / tr.SCORE_FILE
    kept = json.loads(kept_path.read_text())
    assert kept["step"] == run.total_steps and kept["library"] == tr.library_fingerprint()
    kept_path.write_text(json.dumps({**kept, "library": "stale", "psnr": -1.0}))
    fresh = tr.run_training(scene_dir, runs, out, "cmd --quick", quick=True, run=run)
    assert [r["score_cached"] for r in fresh["rows"]] == [True, False]
    assert fresh["rows"][1]["psnr"] == rows[1]["psnr"] and json.loads(kept_path.read_text())["psnr"] == rows[1]["psnr"]
    assert "Preset rule" in (out / f"{stem}.md").read_text()


def test_combine_scenes_averages_changes_against_the_preset(tmp_path):
    tr = _training()

    def study(scene, rows):
        return {"preset": "p", "scene": f"/x/{scene}", "command": f"cmd {scene}", "rows": rows, "split": "test",
                "machine": {"platform": "here"}, "jax": "0", "wall_s": 1.0}

    # scene a: K=16 +1 dB for 1.2x; scene b: K=16 -0.2 dB for 1.4x (mean +0.4 dB, 1.3x: over budget);
    # steps x0.5: +0.1 / +0.1 dB at half the time on both
    a = [_row("own", 20.0, 100, 10, "own"), _row("own, seed 1", 20.2, 100, 10, "seed"),
         _row("K=16", 21.0, 120, 12), _row("steps x0.5", 20.1, 50, 10, "steps")]
    b = [_row("own", 30.0, 200, 20, "own"), _row("own, seed 1", 29.9, 200, 20, "seed"),
         _row("K=16", 29.8, 280, 24), _row("steps x0.5", 30.1, 100, 20, "steps"), _row("only b", 31.0, 10, 1)]
    for scene, rows in (("a", a), ("b", b)):
        (tmp_path / f"accuracy_vs_time_training_p_{scene}.json").write_text(json.dumps(study(scene, rows)))
    (tmp_path / "accuracy_vs_time_training_q_c.json").write_text(json.dumps({**study("c", a), "preset": "q"}))
    res = tr.combine_scenes(tmp_path, "p")
    assert res["scenes"] == ["a", "b"]
    rows = {r["label"]: r for r in res["rows"]}
    assert set(rows) == {"own", "own, seed 1", "K=16", "steps x0.5"}  # only candidates every scene has
    assert rows["K=16"]["psnr"] == pytest.approx(0.4) and rows["K=16"]["train_s"] == pytest.approx(1.3)
    assert rows["K=16"]["per_scene_db"] == [pytest.approx(1.0), pytest.approx(-0.2)]
    assert rows["own"]["psnr"] == 0 and rows["own"]["train_s"] == 1
    ch = res["choice"]
    assert ch["seed_noise_db"] == pytest.approx(0.15)  # mean |seed - own| over the scenes
    assert ch["label"] == "steps x0.5" and not ch["confirmed"]  # K=16 is over the budget on the mean
    for ext in ("json", "md", "png"):
        assert (tmp_path / f"accuracy_vs_time_training_p.{ext}").stat().st_size > 0
    md = (tmp_path / "accuracy_vs_time_training_p.md").read_text()
    assert "| K=16 | +1.00 | -0.20 | +0.40 | 1.30 |" in md and "Pick: **steps x0.5**" in md
    assert tr.combine_scenes(tmp_path, "none") is None
    # a study of another config of the same preset name is not mixed in
    (tmp_path / "accuracy_vs_time_training_p_z.json").write_text(json.dumps({**study("z", a), "preset_key": "other"}))
    with pytest.raises(ValueError, match="different preset configs"):
        tr.combine_scenes(tmp_path, "p")
    assert tr.combine_scenes(tmp_path, "p", key="other")["scenes"] == ["z"]
    (tmp_path / "accuracy_vs_time_training_p_z.json").unlink()
    again = tr.rewrite_summary(tmp_path, "p")  # per-scene summaries rewritten, then the combined one
    assert again["choice"] == ch and (tmp_path / "accuracy_vs_time_training_p_a.md").is_file()
