"""The pixel-grid study: the ground truth's one-ray floor and a model rendered with n x n rays per pixel."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from experiments import pixel_grid
from ne_jax.benchmark.generate import generate_scene
from ne_jax.train.loop import train

from tests.mini_presets import mini_benchmark, mini_run


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("grid")
    sharp = mini_benchmark(test_views=2)  # one ray per pixel: the ground truth is its own floor
    smooth = dataclasses.replace(sharp, name="mini_ss", supersample=3)  # 3 x 3 rays per pixel
    generate_scene("glossy", sharp, root / "sharp", seed=0, edits=[])
    generate_scene("glossy", smooth, root / "smooth", seed=0, edits=[])
    train(mini_run(epochs=1, steps_per_epoch=2, round_epochs=(1, 0)), root / "smooth" / "glossy", root / "run",
          progress=False, log=lambda s: None)
    return root


@pytest.mark.slow  # a study run end to end: -m slow
def test_floor_and_rows(trained, tmp_path, monkeypatch):
    monkeypatch.setattr(pixel_grid, "RESULTS", tmp_path)
    run = str(trained / "run")
    pixel_grid.main(["--run", "smooth", run, str(trained / "smooth" / "glossy"),
                     "--run", "sharp", run, str(trained / "sharp" / "glossy"),
                     "--samples", "1", "2", "--views", "0", "1", "--out", "t"])
    res = json.loads((tmp_path / "pixel_grid_t.json").read_text())
    smooth, sharp = res["runs"]
    # the same rays as the stored ground truth: only its 8-bit rounding differs
    assert sharp["floor"]["psnr"] > 45 and sharp["floor"]["ground_truth_rays_per_pixel"] == 1
    # one centre ray against a 3 x 3 average: the silhouettes and textures differ
    assert 10 < smooth["floor"]["psnr"] < 40 and smooth["floor"]["ground_truth_rays_per_pixel"] == 9
    assert [r["pixel_samples"] for r in smooth["rows"]] == [1, 2] and smooth["trained_pixel_samples"] == 1
    for r in smooth["rows"]:
        assert np.isfinite(r["psnr"]) and 0 <= r["silhouette_error_share"] <= 1 and r["seconds_per_image"] > 0
    assert smooth["rows"][0]["psnr"] != smooth["rows"][1]["psnr"]  # a grid renders other rays
    md = (tmp_path / "pixel_grid_t.md").read_text()
    assert "| smooth |" in md and "| **1** |" in md and "| 4 |" in md


def test_bad_arguments_are_named(trained):
    run, scene = str(trained / "run"), str(trained / "smooth" / "glossy")
    with pytest.raises(SystemExit, match=r"--views: expected test views 0\.\.1 .* found \[5\]"):
        pixel_grid.main(["--run", "a", run, scene, "--views", "5", "--out", "t"])
    with pytest.raises(SystemExit, match="--samples: expected rays per pixel side >= 1"):
        pixel_grid.main(["--run", "a", run, scene, "--samples", "0", "--out", "t"])
