"""Declared effects: the spec language, scene.json declarations, the benchmark's declarations and
its matte / no-alpha variants, ``auto``, and the command line recording what a run used."""

from __future__ import annotations

import json

import pytest

from ne_jax.benchmark.generate import BenchmarkPreset, generate_scene
from ne_jax.benchmark.scenes import get_scene
from ne_jax.cli import main
from ne_jax.data.nerf_synthetic import load_split
from ne_jax.pointcloud.init import Views
from ne_jax.train.effects import (
    EffectsError,
    auto_effects,
    declare_effects,
    effects_of,
    parse_effects,
    scene_effects,
)
from ne_jax.train.loop import initial_cloud
from ne_jax.train.model import load_trained
from ne_jax.train.run import get_run_preset

from tests.mini_presets import mini_benchmark

TINY = get_run_preset("tiny")
LIKE_TINY = BenchmarkPreset("like_tiny", 64, 24, 1, 1, 1, 0.75, 2000)  # the tiny preset's views and detail


def test_spec_parsing_and_its_errors():
    assert parse_effects("specular=off, background_model=sphere") == {"specular": "off", "background_model": "sphere"}
    assert parse_effects("specular=false") == {"specular": "off"}
    known = r"expected one of \['background_model', 'specular'\]"
    with pytest.raises(EffectsError, match=r"unknown effect 'shadows'; " + known):
        parse_effects("shadows=on")
    with pytest.raises(EffectsError, match=r"unknown effect 'background'; " + known):  # the colour is not an effect
        parse_effects("background=sphere")
    with pytest.raises(EffectsError, match=r"'background_model' expected one of \['constant', 'sphere'\], found 'sky'"):
        parse_effects("background_model=sky")
    with pytest.raises(EffectsError, match="expected name=value pairs .*found 'specular'"):
        parse_effects("specular")


def test_scene_json_declares_and_bad_declarations_name_the_file(tmp_path):
    assert scene_effects(tmp_path) is None  # no scene.json
    (tmp_path / "scene.json").write_text(json.dumps({"effects": {"specular": False, "background_model": "constant"}}))
    assert scene_effects(tmp_path) == {"specular": "off", "background_model": "constant"}
    render, record = declare_effects(TINY.render, "scene", tmp_path)
    assert not render.shading.effects.specular and record == {
        "spec": "scene", "source": "scene.json", "effects": {"specular": "off", "background_model": "constant"}}
    # the command line overrides; "all" turns every effect on
    render, record = declare_effects(TINY.render, "specular=on", tmp_path)
    assert render.shading.effects.specular and record["source"] == "command line"
    assert effects_of(declare_effects(TINY.render, "all", tmp_path)[0]) == {"specular": "on",
                                                                            "background_model": "sphere"}
    (tmp_path / "scene.json").write_text(json.dumps({"effects": {"glitter": True}}))
    with pytest.raises(EffectsError, match=rf"{tmp_path / 'scene.json'}: unknown effect 'glitter'"):
        scene_effects(tmp_path)
    # a folder without a declaration keeps the preset's effects
    empty = tmp_path / "empty"
    empty.mkdir()
    render, record = declare_effects(TINY.render, "scene", empty)
    assert render == TINY.render and record["source"] == "preset"


@pytest.fixture(scope="module")
def variants(tmp_path_factory):
    """glossy as the tiny preset renders it (with its ``bend`` edit), its matte variant and a variant
    without alpha; blocks (the variants and blocks without edits)."""
    root = tmp_path_factory.mktemp("effects")
    out = {}
    for name, preset, edits in (
            ("glossy", LIKE_TINY, ("bend",)),
            ("matte", BenchmarkPreset("matte", 64, 24, 1, 1, 1, 0.75, 2000, matte=True), ()),
            ("opaque", BenchmarkPreset("opaque", 24, 5, 1, 1, 1, 0.4, 400, alpha=False), ())):
        generate_scene("glossy", preset, root / name, 0, edits=edits)
        out[name] = root / name / "glossy"
    generate_scene("blocks", LIKE_TINY, root / "blocks", 0, edits=())
    out["blocks"] = root / "blocks" / "blocks"
    return out


def test_the_benchmark_declares_what_its_renderer_does(variants):
    assert scene_effects(variants["glossy"]) == {"specular": "on", "background_model": "constant"}
    assert scene_effects(variants["glossy"] / "edits" / "bend") == {"specular": "on", "background_model": "constant"}
    assert scene_effects(variants["blocks"]) == {"specular": "off", "background_model": "constant"}  # Lambertian only
    assert scene_effects(variants["matte"]) == {"specular": "off", "background_model": "constant"}
    assert scene_effects(variants["opaque"]) == {"specular": "on", "background_model": "sphere"}
    opaque = load_split(variants["opaque"], "train").images
    assert (opaque[..., 3] == 1.0).all() and (opaque[..., :3] > 0.99).all(axis=-1).mean() > 0.3  # white around
    assert get_scene("glossy", 0.4).materials[0].ks > 0  # the variant does not change the scene itself


@pytest.mark.parametrize("name, specular", [("glossy", "on"), ("blocks", "off")])
def test_auto_decides_specular_from_the_views(variants, name, specular):
    split = load_split(variants[name], "train")
    cloud = initial_cloud(TINY.init, variants[name], Views.from_split(split))
    effects, evidence = auto_effects(split, cloud.xyz)
    assert effects == {"specular": specular, "background_model": "constant"}, evidence
    assert evidence["specular_points"] > 1000


def test_auto_background_from_alpha_and_no_cloud_keeps_specular(variants):
    effects, evidence = auto_effects(load_split(variants["opaque"], "train"), None)
    assert effects == {"background_model": "sphere", "specular": "on"} and evidence["opaque_pixels"] == 1.0
    assert "carving needs alpha masks" in evidence["note"]


def test_cli_train_records_the_effects_it_used(tmp_path, capsys):
    scene = tmp_path / "bench"
    generate_scene("blocks", mini_benchmark(), scene, 0, edits=())  # declares specular off
    run = tmp_path / "run"
    assert main(["train", str(scene / "blocks"), "--out", str(run), "--epochs", "1", "--steps-per-epoch", "2",
                 "--quiet", "--no-eval"]) == 0
    assert "effects: specular=off, background_model=constant (scene.json)" in capsys.readouterr().out
    notes = json.loads((run / "metrics.json").read_text())["notes"]
    assert notes["effects"] == {"spec": "scene", "source": "scene.json",
                                "effects": {"specular": "off", "background_model": "constant"}}
    model = load_trained(run)  # the run's config carries it to eval and edit
    assert not model.run.render.shading.effects.specular
    assert not {"specular", "tint", "roughness", "bottleneck"} & set(model.state.params["shader"])  # no parameters
    assert main(["train", str(scene / "blocks"), "--out", str(tmp_path / "bad"), "--effects", "shine=on"]) == 2
    assert "unknown effect 'shine'" in capsys.readouterr().err and not (tmp_path / "bad").exists()


def test_a_scene_json_with_an_unknown_effect_name_is_refused(tmp_path):
    (tmp_path / "scene.json").write_text(json.dumps({"effects": {"specular": True, "background": "sphere"}}))
    with pytest.raises(EffectsError, match=r"scene.json: unknown effect 'background'; expected one of"):
        scene_effects(tmp_path)
