"""The effects study's runs per scene: the declaration, each left-out effect alone, every effect."""

from __future__ import annotations

import json

from experiments import effects_study
from ne_jax.train.effects import declare_effects
from ne_jax.train.run import get_run_preset


def _scene(tmp_path, name, effects):
    folder = tmp_path / name
    folder.mkdir()
    (folder / "scene.json").write_text(json.dumps({"effects": effects}))
    return folder


def test_each_effect_adds_one_run_per_left_out_effect_only_where_several_are(tmp_path):
    lambertian = _scene(tmp_path, "blocks", {"specular": False, "background_model": "constant"})
    shiny = _scene(tmp_path, "glossy", {"specular": True, "background_model": "constant"})
    assert effects_study.specs_for("tiny", lambertian, False) == ["scene", "all"]
    specs = effects_study.specs_for("tiny", lambertian, True)
    assert specs == ["scene", "specular=on,background_model=constant", "specular=off,background_model=sphere", "all"]
    # each spec switches on exactly one more effect than the declaration; together they span scene .. all
    base = get_run_preset("tiny").render
    got = [tuple(declare_effects(base, s, lambertian)[1]["effects"].values()) for s in specs]
    assert got == [("off", "constant"), ("on", "constant"), ("off", "sphere"), ("on", "sphere")]
    assert effects_study.specs_for("tiny", shiny, True) == ["scene", "all"]  # one left out: that is ``all``


def test_a_spec_the_scene_does_not_train_is_refused_before_any_training(tmp_path, capsys):
    _scene(tmp_path, "glossy", {"specular": True, "background_model": "constant"})
    try:
        effects_study.main(["--root", str(tmp_path), "--scenes", "glossy", "--runs", str(tmp_path / "runs"),
                            "--specs", "scene", "specular=off"])
    except SystemExit as exit_:
        assert exit_.code == 2
    else:
        raise AssertionError("an unknown --specs entry must stop the study")
    err = capsys.readouterr().err
    assert "--specs specular=off" in err and "glossy trains only scene, all" in err
    assert not (tmp_path / "runs").exists()
