"""The accuracy-vs-time study (``python -m experiments.accuracy_vs_time``): its candidates, the preset
rule, the summary over scenes and a quick run end to end; and ``experiments/compare_runs.py``."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest


def _training():
    """The module ``experiments.accuracy_vs_time``."""
    import importlib

    return importlib.import_module("experiments.accuracy_vs_time")


@pytest.fixture(scope="module")
def mini(tmp_path_factory):
    """``(root, scene_dir, run)``: a 24-px generated glossy scene (as tests/edit/test_model.py), no edits,
    and a RunConfig of a few steps."""
    from ne_jax.benchmark.generate import generate_scene

    from tests.mini_presets import mini_benchmark, short_run

    root = tmp_path_factory.mktemp("avt_mini")
    generate_scene("glossy", mini_benchmark(train_views=4), root / "bench", seed=0, edits=())
    return root, root / "bench" / "glossy", short_run()


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
    # one program, not flax's eager operations
    init = jax.jit(init_train_state, static_argnums=(0, 1), static_argnames="total_steps")
    model = TrainedModel(run=run, state=init(run.train, run.render, points, k_model, total_steps=run.total_steps),
                         scene=PointScene.build(points, run.render, run.capacities), scene_dir=scene_dir)
    epochs = [{"epoch": 1, "psnr": 12.5, "train_seconds": 3.0}]
    return save_trained(model, tmp_path_factory.mktemp("initial_model") / "run", metrics={"epochs": epochs})


def test_compare_runs_same_and_different(initial_model, tmp_path, capsys):
    """``python -m experiments.compare_runs``: a run against a copy of itself, also read by a checkout in
    another process, is equal bit for bit, its test render too (exit 0); a copy whose checkpoint holds
    other parameters is not (exit 1). (What the runs trained does not matter:
    the run directory holds a model as training starts it.)"""
    import importlib
    import shutil

    compare = importlib.import_module("experiments.compare_runs")
    run_dir = initial_model
    assert compare.main([str(run_dir), str(run_dir)]) == 0
    out = capsys.readouterr().out
    assert "every array equal bit for bit: True" in out and "render.rgb: 0" in out
    from experiments.common import ROOT

    assert compare.main([str(run_dir), str(run_dir), "--checkout-b", str(ROOT)]) == 0  # read in a fresh process
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


def test_training_study_needs_a_scene(capsys):
    avt = _training()
    assert avt.main([]) == 2
    assert "needs a scene to train on: pass --scene DIR" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        avt.main(["--scene", "x", "--preset", "huge"])
    assert "invalid choice: 'huge'" in capsys.readouterr().err


def test_training_study_cli_passes_finished_only(mini, tmp_path):
    """``--finished-only`` reaches the study: with no finished runs it refuses before training anything."""
    avt = _training()
    _, scene_dir, _ = mini
    with pytest.raises(FileNotFoundError, match="finished_only: the preset's own run .* has not finished"):
        avt.main(["--scene", str(scene_dir), "--quick", "--runs", str(tmp_path / "runs"),
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
    assert half.steps_per_epoch == own.steps_per_epoch // 2 and half.epochs == own.epochs
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
