"""The pixel-grid study: the ground truth's one-ray floor and a model rendered with n x n rays per pixel.

The default tests score the ground truth's floor for real (the ray caster, no model) and run the
command line with the model's renders stood in for: its arguments, one row per grid and the JSON and
table it writes. The study on a trained model runs with ``-m slow``."""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import numpy as np
import pytest

from experiments import pixel_grid
from ne_jax.benchmark.generate import generate_scene
from ne_jax.config_json import config_key
from ne_jax.train.loop import train

from tests.mini_presets import mini_benchmark, mini_run


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """The glossy scene twice (no edits): its ground truth at one ray per pixel (``sharp``) and as the
    mean of 3 x 3 rays (``smooth``)."""
    root = tmp_path_factory.mktemp("grid")
    sharp = mini_benchmark(test_views=2)  # one ray per pixel: the ground truth is its own floor
    smooth = dataclasses.replace(sharp, name="mini_ss", supersample=3)  # 3 x 3 rays per pixel
    generate_scene("glossy", sharp, root / "sharp", seed=0, edits=[])
    generate_scene("glossy", smooth, root / "smooth", seed=0, edits=[])
    return root


@pytest.fixture(scope="module")
def trained(scenes):
    train(mini_run(epochs=1, steps_per_epoch=2, round_epochs=(1, 0)), scenes / "smooth" / "glossy", scenes / "run",
          progress=False, log=lambda s: None)
    return scenes


def _stand_in_model(monkeypatch, pixel_samples=1):
    """A model that only carries its run config, returned by ``load_trained`` for any run directory."""
    run = mini_run()
    run = run.replace(render=run.render.replace(pixel_samples=pixel_samples))
    model = SimpleNamespace(run=run, background=run.background)
    monkeypatch.setattr("ne_jax.train.model.load_trained", lambda run_dir: model)
    return model


def _check_floors(smooth, sharp):
    # the same rays as the stored ground truth: only its 8-bit rounding differs
    assert sharp["floor"]["psnr"] > 45 and sharp["floor"]["ground_truth_rays_per_pixel"] == 1
    # one centre ray against a 3 x 3 average: the silhouettes and textures differ
    assert 10 < smooth["floor"]["psnr"] < 40 and smooth["floor"]["ground_truth_rays_per_pixel"] == 9


@pytest.mark.slow  # a study run end to end: -m slow
def test_floor_and_rows(trained, tmp_path, monkeypatch):
    monkeypatch.setattr(pixel_grid, "RESULTS", tmp_path)
    run = str(trained / "run")
    pixel_grid.main(["--run", "smooth", run, str(trained / "smooth" / "glossy"),
                     "--run", "sharp", run, str(trained / "sharp" / "glossy"),
                     "--samples", "1", "2", "--views", "0", "1", "--out", "t"])
    res = json.loads((tmp_path / "pixel_grid_t.json").read_text())
    smooth, sharp = res["runs"]
    _check_floors(smooth, sharp)
    assert [r["pixel_samples"] for r in smooth["rows"]] == [1, 2] and smooth["trained_pixel_samples"] == 1
    for r in smooth["rows"]:
        assert np.isfinite(r["psnr"]) and 0 <= r["silhouette_error_share"] <= 1 and r["seconds_per_image"] > 0
    assert smooth["rows"][0]["psnr"] != smooth["rows"][1]["psnr"]  # a grid renders other rays
    md = (tmp_path / "pixel_grid_t.md").read_text()
    assert "| smooth |" in md and "| **1** |" in md and "| 4 |" in md


def test_floors_and_one_row_per_grid_are_written(scenes, tmp_path, monkeypatch):
    """The ground truth's floor scored for real on both scenes; the model's rows (stood in for) one per
    ``--samples`` entry on the views asked for, its own grid in bold in the table."""
    model = _stand_in_model(monkeypatch, pixel_samples=2)
    monkeypatch.setattr(pixel_grid, "RESULTS", tmp_path)
    asked = []

    def grid_row(m, split, views, n):
        assert m is model and views == [0, 1] and split.num_views == 2
        asked.append(n)
        return {"pixel_samples": n, "psnr": 20.0 + n, "psnr_per_view": [20.0, 21.0],
                "silhouette_error_share": 0.5, "seconds_per_image": 0.25}

    monkeypatch.setattr(pixel_grid, "grid_row", grid_row)
    pixel_grid.main(["--run", "smooth", "RUN", str(scenes / "smooth" / "glossy"),
                     "--run", "sharp", "RUN", str(scenes / "sharp" / "glossy"),
                     "--samples", "1", "2", "--views", "0", "1", "--out", "t"])
    assert asked == [1, 2, 1, 2]
    res = json.loads((tmp_path / "pixel_grid_t.json").read_text())
    smooth, sharp = res["runs"]
    _check_floors(smooth, sharp)
    assert [r["name"] for r in res["runs"]] == ["smooth", "sharp"] and res["views"] == [0, 1]
    assert smooth["config_key"] == config_key(model.run) and smooth["trained_pixel_samples"] == 2
    assert [r["pixel_samples"] for r in smooth["rows"]] == [1, 2]
    assert res["command"].endswith("--samples 1 2 --views 0 1 --out t") and res["seconds"] >= 0
    md = (tmp_path / "pixel_grid_t.md").read_text()
    floor = f"{smooth['floor']['psnr']:.2f}"
    assert f"| smooth | {config_key(model.run)} | {floor} | 1 | 21.00 | 50% | 0.25 |" in md
    assert "| **4** | 22.00 |" in md and md.count("| **4** |") == 2  # each run's own grid in bold


def test_bad_arguments_are_named(scenes, monkeypatch):
    _stand_in_model(monkeypatch)
    scene = str(scenes / "smooth" / "glossy")
    with pytest.raises(SystemExit, match=r"--views: expected test views 0\.\.1 .* found \[5\]"):
        pixel_grid.main(["--run", "a", "RUN", scene, "--views", "5", "--out", "t"])
    with pytest.raises(SystemExit, match="--samples: expected rays per pixel side >= 1"):
        pixel_grid.main(["--run", "a", "RUN", scene, "--samples", "0", "--out", "t"])
