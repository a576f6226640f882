"""experiments.gpu_check at its toy size (``--tiny``) on the CPU: each part runs and reports what the
docs quote; the budget decides the ``paper`` run's length; the command writes its results named after
the device."""

from __future__ import annotations

import json
import math

import pytest

from experiments import gpu_check as G


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The toy sizes and their two generated scenes (16 and 24 px)."""
    root = tmp_path_factory.mktemp("gpu_check_scenes")
    s = G.sizes(tiny=True)
    return s, G.scene_dir(s.small, root, log=lambda m: None), G.scene_dir(s.large, root, log=lambda m: None)


def test_rates_of_a_step_and_a_render(tiny):
    s, small, _ = tiny
    run = G.declared(G.presets(s)["default"], small)
    r = G.rates(run, small, s.rate_steps, s.repeats)
    assert r["points"] == run.init.carve.num_points
    assert r["batch_rays"] == run.sampler.batch_size == 128
    assert r["image_rays"] == 16 * 16 * run.render.pixel_samples ** 2
    assert r["train_rays_per_s"] > 0 and r["render_rays_per_s"] > 0
    # rays per second are rounded to a whole number (a slow toy step on a loaded machine: 161 for 160.8)
    assert math.isclose(r["train_rays_per_s"], r["batch_rays"] / (r["ms_per_step"] / 1e3), rel_tol=1e-3, abs_tol=0.5)
    assert r["memory"]["host_peak_rss_bytes"] > 0 and r["memory"]["device_peak_bytes"] is None  # a CPU keeps none


@pytest.mark.filterwarnings("ignore:carve_visual_hull")  # a 16 px scene's hull reaches the bounds
def test_a_whole_default_run_with_its_round(tiny, tmp_path):
    s, small, _ = tiny
    run = G.declared(G.presets(s)["default"], small)
    r = G.default_run(run, small, tmp_path / "default", views=1, log=lambda m: None)
    assert r["steps"] == 6 and [e["epoch"] for e in r["epochs"]] == [1, 2, 3]
    assert [e["round_s"] is not None for e in r["epochs"]] == [False, True, False]  # a round after epoch 2
    assert r["initial_cloud"]["source"] == "carving"
    assert r["test"]["views"] == 1 and math.isfinite(r["test"]["psnr"]) and r["test"]["s_per_view"] > 0


@pytest.mark.filterwarnings("ignore:carve_visual_hull")
def test_the_paper_run_resumes_epoch_by_epoch_and_projects_the_full_run(tiny, tmp_path):
    s, _, large = tiny
    run = G.declared(G.presets(s)["paper"], large)
    r = G.paper_run(run, large, tmp_path / "paper", s_per_step=0.5, budget_s=600.0, views=s.score_views,
                    s_per_view=1.0, tiny=True, log=lambda m: None)
    assert [c["resumed"] for c in r["calls"]] == [False, True, True, True] and r["stopped"] is None
    assert [e["round_s"] is not None for e in r["epochs"]] == [False, True, False, False]
    assert r["test"]["views"] == 2 and len(r["test"]["view_s"]) == 2
    p = r["projected"]
    assert p["train_s"] == round(G.PAPER_STEPS * r["s_per_step"])
    assert p["eval_s"] == round(G.TEST_VIEWS * r["test"]["s_per_view"])
    assert p["rounds_s"] == round(G.PAPER_ROUNDS * r["epochs"][1]["round_s"])
    assert p["total_h"] > 0


def test_the_budget_sizes_and_stops_the_paper_run():
    # 400 s left, 4 views at 2 s (+2 for the compile): half of 388 s for 4 epochs at 10 ms a step
    assert G.steps_per_epoch(400.0, 0.01, 4, 4, 2.0) == 4850
    assert G.steps_per_epoch(5.0, 0.01, 4, 4, 2.0) == 10  # never fewer than 10
    first = [{"s": 100.0}]  # only the first epoch (carving, compile) to go by
    assert G.next_epoch_fits(150.0, first, 260.0, 4, 2.0) is True  # 150 + 100 + 5 views at 2 s
    assert G.next_epoch_fits(150.0, first, 259.0, 4, 2.0) is False
    later = [{"s": 100.0}, {"s": 30.0}]  # later epochs are shorter: they decide
    assert G.next_epoch_fits(250.0, later, 290.0, 4, 2.0) is True
    assert G.next_epoch_fits(251.0, later, 290.0, 4, 2.0) is False


def _canned(name):
    rate = {"points": 10, "tree_depth": 4, "batch_rays": 8, "ms_per_step": 1.0, "train_rays_per_s": 8000,
            "image_px": 4, "ms_per_image": 2.0, "render_rays_per_s": 8000, "step_compile_s": 1.0,
            "image_compile_s": 1.0, "memory": {"device_peak_bytes": None, "host_peak_rss_bytes": 1}}
    epochs = [{"epoch": 1, "steps": 2, "train_s": 1.0, "psnr_train": 10.0, "alive": 10, "round_s": 0.5,
               "compiles": 1}]
    test = {"views": 1, "image_px": 4, "psnr": 20.0, "ssim": 0.5, "lost_segments": 0, "view_s": [1.0],
            "s_per_view": 1.0}
    run = {"config_key": "abc", "run_dir": "x", "steps": 2, "batch_rays": 8, "wall_s": 1.0, "epochs": epochs,
           "initial_cloud": {"source": "carving", "points": 10, "seconds": 0.1}, "test": test,
           "memory": rate["memory"]}
    if name == "paper":
        run.update(epochs_planned=4, steps_per_epoch=2, stopped=None, calls=[], s_per_step=0.5,
                   train_rays_per_s=16, projected={"steps": 80000, "rounds": 9, "test_views": 200, "train_s": 1,
                                                    "rounds_s": 1, "initial_cloud_s": 1, "eval_s": 1, "total_h": 0.1})
    return rate, run


def test_the_command_writes_its_results_after_each_part_named_after_the_device(tmp_path, monkeypatch):
    saved = []
    monkeypatch.setattr(G, "scene_dir", lambda preset, root, log=print: tmp_path / preset.name)
    monkeypatch.setattr(G, "declared", lambda run, scene: run)
    monkeypatch.setattr(G, "rates", lambda run, scene, steps, repeats: _canned(run.name)[0])
    monkeypatch.setattr(G, "default_run", lambda *a, **k: _canned("default")[1])

    def paper(run, scene, run_dir, s_per_step, budget_s, *a, **k):
        saved.append(json.loads((tmp_path / "out" / "gpu_check_tiny_cpu.json").read_text()))
        assert 0 < budget_s <= 100 and s_per_step == 1e-3  # what is left of the budget; the rate's step
        return _canned("paper")[1]

    monkeypatch.setattr(G, "paper_run", paper)
    assert G.main(["--tiny", "--budget-s", "100", "--out-dir", str(tmp_path / "out"), "--commit", "feed"]) == 0
    assert saved[0]["complete"] is False and set(saved[0]["rates"]) == {"default", "paper"}
    res = json.loads((tmp_path / "out" / "gpu_check_tiny_cpu.json").read_text())
    assert res["complete"] is True and res["commit"] == "feed"
    assert res["command"] == "python -m experiments.gpu_check --tiny --budget-s 100 --out-dir " \
        f"{tmp_path / 'out'} --commit feed"
    assert res["devices"]["platform"] == "cpu" and res["devices"]["kind"]
    md = (tmp_path / "out" / "gpu_check_tiny_cpu.md").read_text()
    assert "GPU check on cpu" in md and "Projected full run" in md


@pytest.mark.slow
def test_the_whole_tiny_check(tmp_path):
    out = tmp_path / "out"
    assert G.main(["--tiny", "--scene-root", str(tmp_path / "scenes"), "--run-root", str(tmp_path / "runs"),
                   "--out-dir", str(out)]) == 0
    res = json.loads((out / "gpu_check_tiny_cpu.json").read_text())
    assert res["complete"] and res["paper_run"]["projected"]["total_h"] > 0
