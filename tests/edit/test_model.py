"""Editing a trained model end to end: edited run directories, zero-shot rendering, fine-tuning
(with and without trainable ISTs) and the command line, on a tiny generated scene."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest

from ne_jax.benchmark.edits import benchmark_edit
from ne_jax.benchmark.generate import BenchmarkPreset, generate_scene
from ne_jax.cli import main
from ne_jax.data.nerf_synthetic import load_split
from ne_jax.edit.model import edit_model, finetune
from ne_jax.edit.targets import EditError
from ne_jax.eval import evaluate_model
from ne_jax.pointcloud.rounds import RoundConfig
from ne_jax.render.quadrature import QuadratureConfig
from ne_jax.train import SamplerConfig, TrainConfig
from ne_jax.train.loop import train
from ne_jax.train.model import load_trained
from ne_jax.train.run import InitConfig, RunConfig

from tests.mini_presets import MINI_CAPS, tiny_render

MINI = BenchmarkPreset("mini", resolution=24, train_views=4, val_views=1, test_views=1, supersample=1,
                       detail=0.4, surface_samples=2000)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    generate_scene("glossy", MINI, root, seed=0)
    return root / "glossy"


@pytest.fixture(scope="module")
def trained(scene_dir, tmp_path_factory):
    render = tiny_render(quadrature=QuadratureConfig(samples_per_level=(3, 4, 5)))
    init = InitConfig(carve=dataclasses.replace(InitConfig().carve, resolution=40, num_points=1200))
    run = RunConfig(name="test", render=render, capacities=MINI_CAPS, sampler=SamplerConfig(batch_size=128),
                    train=TrainConfig(lr=5e-3),
                    init=init, rounds=RoundConfig(grow_rays=256, grow_chunk=128, outlier_neighbors=16),
                    epochs=1, steps_per_epoch=2, round_epochs=(1, 0))
    out = tmp_path_factory.mktemp("run") / "trained"
    train(run, scene_dir, out, progress=False, log=lambda s: None)
    return out


def _psnr(model):
    split = load_split(model.scene_dir, "test")
    report, _ = evaluate_model(model, split, progress=False)
    return report["psnr"]


@pytest.fixture(scope="module")
def bent(trained, tmp_path_factory):
    """The trained model edited by the scene's "bend", written to a run directory (shared: one edit)."""
    out = tmp_path_factory.mktemp("edited") / "bend"
    model = load_trained(trained)
    edit, truth = benchmark_edit(model.scene_dir, "bend")
    edited, report = edit_model(model, edit, out, scene_dir=truth)
    return model, edited, report, out


def test_edit_by_name_writes_a_run_directory_that_renders_zero_shot(bent, scene_dir):
    model, edited, report, out = bent
    assert report["moved"] > 0 and report["good"] > 0.9 * report["alive"]
    assert edited.run.render.shading.effects.ist and edited.scene_dir == scene_dir / "edits" / "bend"
    back = load_trained(out)  # every run command reads it
    np.testing.assert_array_equal(np.asarray(back.scene.points.xyz), np.asarray(edited.scene.points.xyz))
    np.testing.assert_array_equal(np.asarray(back.scene.points.ist), np.asarray(edited.scene.points.ist))
    assert back.scene_dir == (scene_dir / "edits" / "bend").resolve()
    # the colour model is untouched and the edited model renders finite images of the edited scene
    for a, b in zip(np.asarray(model.state.params["shader"]["density"]["kernel"]).ravel(),
                    np.asarray(back.state.params["shader"]["density"]["kernel"]).ravel()):
        assert a == b
    assert np.isfinite(_psnr(back))
    meta = json.loads((out / "metrics.json").read_text())
    assert meta["edit"]["edit"] == "bend"


def test_unknown_edit_name_lists_the_scenes_edits(trained, tmp_path, capsys):
    assert main(["edit", str(trained), "--edit", "fold", "--out", str(tmp_path / "e")]) == 2
    err = capsys.readouterr().err
    assert "'fold'" in err and "bend" in err and "tilt_ring" in err
    assert not (tmp_path / "e").exists()  # nothing written


def test_edit_of_a_non_benchmark_scene_by_name_is_refused(trained, tmp_path):
    model = dataclasses.replace(load_trained(trained), scene_dir=tmp_path)
    with pytest.raises(EditError, match="expected the model's scene folder to be a benchmark scene"):
        benchmark_edit(model.scene_dir, "bend")


def test_ground_truth_of_another_edit_definition_is_refused(scene_dir, tmp_path):
    """A benchmark generated before an edit's definition changed names the folder and the two
    definitions instead of scoring against the wrong images."""
    copy = tmp_path / "scene"
    shutil.copytree(scene_dir, copy)
    meta_path = copy / "edits" / "bend" / "scene.json"
    meta = json.loads(meta_path.read_text())
    meta["edit_description"] = "bend by 10 deg"
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(EditError, match=r"generated for the edit 'bend by 10 deg'.*regenerate"):
        benchmark_edit(copy, "bend")
    assert benchmark_edit(copy, "cut")[1] == copy / "edits" / "cut"  # the other edits still resolve


def _check_finetuned(before, after, history, run_dir, train_ist):
    """Features always trained; the ISTs exactly when ``train_ist`` (kept orthogonal)."""
    assert not np.array_equal(np.asarray(before.feature), np.asarray(after.feature))
    ist_changed = not np.array_equal(np.asarray(before.ist), np.asarray(after.ist))
    assert ist_changed == train_ist
    record = history[-1]
    assert ("loss/ist_orthogonality" in record) == train_ist and record["skipped"] == 0
    if train_ist:  # kept orthogonal
        ist = np.asarray(after.ist)[np.asarray(after.alive)]
        gram = np.einsum("cji,cjk->cik", ist, ist)
        assert np.abs(gram - np.eye(3)).max() < 0.05
    assert load_trained(run_dir).run.train.train_ist == train_ist


def test_finetune_trains_features_and_the_ist(bent, tmp_path):
    """``train_ist=True`` through the API; ``train_ist=False`` (the default) is fine-tuned through the
    command line in :func:`test_cli_edit_and_finetune` with the same checks (one compile each)."""
    _, edited, _, _ = bent
    result = finetune(edited, tmp_path / "ft", 1, steps_per_epoch=2, train_ist=True, progress=False,
                      log=lambda s: None)
    _check_finetuned(edited.scene.points, result.scene.points, result.history, tmp_path / "ft", True)


def test_cli_edit_and_finetune(trained, tmp_path, capsys):
    assert main(["edit", str(trained), "--edit", "cut", "--out", str(tmp_path / "e")]) == 0
    out = capsys.readouterr().out
    assert "edit 'cut'" in out and "zero-shot test: PSNR" in out
    assert main(["finetune", str(tmp_path / "e"), "--out", str(tmp_path / "f"), "--steps-per-epoch", "2",
                 "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "test: PSNR" in out and "error by region: " in out
    report = json.loads((tmp_path / "f" / "eval_test" / "metrics.json").read_text())
    assert set(report["regions"]) == {"silhouette", "hole", "see_through", "highlight", "texture", "flat", "background"}
    assert sum(r["error"] for r in report["regions"].values()) == pytest.approx(1.0)
    assert all(0.0 <= v["hole_pixels"] <= 1.0 for v in report["views"])
    assert len(list((tmp_path / "f" / "eval_test" / "error_maps").glob("*.png"))) == report["num_views"]
    # fine-tuning without trainable ISTs (the default): features trained, ISTs untouched
    history = json.loads((tmp_path / "f" / "metrics.json").read_text())["epochs"]
    _check_finetuned(load_trained(tmp_path / "e").scene.points, load_trained(tmp_path / "f").scene.points,
                     history, tmp_path / "f", False)
