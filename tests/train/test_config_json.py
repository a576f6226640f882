"""Configs as typed JSON: round trips, keys of every setting, configs of another version, differences by name."""

import json

import pytest

import ne_jax.config_json as cj

from .test_checkpoint import SMALL_RCFG, SMALL_TCFG
from .test_step import RCFG, TCFG


def test_configs_round_trip_with_types():
    from ne_jax.geometry.kdtree import KDTreeConfig
    from ne_jax.render.renderer import RenderConfig

    paper = RenderConfig(kdtree=KDTreeConfig(depth=21))
    for cfg in (SMALL_TCFG, SMALL_RCFG, paper,
                RCFG.with_effects(background_model="sphere")):
        data = json.loads(json.dumps(cj.config_to_json(cfg)))
        back = cj.config_from_json(data)
        assert back == cfg and type(back) is type(cfg)
    with pytest.raises(cj.ConfigError, match="expected an ne_jax dataclass"):
        cj.config_from_json({"__type__": "os:system", "command": "true"})


def test_buffer_sizes_are_saved_but_not_settings():
    """``RunConfig.capacities`` is written to config.json and read back, but is neither part of the
    run's key nor a difference that refuses a resume; any other field still is."""
    from ne_jax.train.run import RunConfig

    run = RunConfig.tiny()
    bigger = run.replace(capacities=run.capacities.replace(frontier=128, segments_per_ray=None))
    data = json.loads(json.dumps(cj.config_to_json(bigger)))
    assert data["capacities"]["frontier"] == 128 and cj.config_from_json(data) == bigger
    assert cj.config_key(bigger) == cj.config_key(run)
    assert cj.config_diff(cj.config_to_json(bigger), cj.config_to_json(run)) == []
    assert cj.config_key(run.replace(seed=1)) != cj.config_key(run)
    assert cj.config_diff(cj.config_to_json(run.replace(seed=1)), cj.config_to_json(run)) == [
        "seed: checkpoint 1, run 0"]


def test_every_setting_changes_the_key():
    """A setting at any value is part of the key: ``density_falloff`` and ``confidence_lr`` set or at
    their defaults give three keys, and the config reads back from config.json as it was."""
    from ne_jax.train.run import RunConfig

    run = RunConfig.default()
    assert "density_falloff" in json.dumps(cj.config_to_json(run, _for_key=True))
    gated = run.replace(render=run.render.replace(kdtree=run.render.kdtree.replace(density_falloff=1.0)))
    faster = run.replace(train=run.train.replace(confidence_lr=10.0))
    assert len({cj.config_key(run), cj.config_key(gated), cj.config_key(faster)}) == 3
    assert cj.config_from_json(json.loads(json.dumps(cj.config_to_json(gated)))) == gated


def test_a_config_from_another_version_is_refused_or_named():
    """A stored config with a field this version lacks is refused naming the type and the field; one
    missing a field this version has is a difference naming it (so a resume is refused, not guessed)."""
    expected = cj.config_to_json(TCFG)
    extra = json.loads(json.dumps(expected))
    extra["adam_b3"] = 0.5
    with pytest.raises(cj.ConfigError, match=r"TrainConfig'.*no field\(s\) \['adam_b3'\]"):
        cj.config_from_json(extra)
    old = json.loads(json.dumps(expected))
    del old["train_ist"]
    assert cj.config_diff(old, expected) == ["train_ist (missing in checkpoint; run has False)"]
    stored = json.loads(json.dumps(expected).replace("ne_jax.train.state:", "ne_jax.train.loop:"))
    with pytest.raises(cj.ConfigError, match="does not exist"):
        cj.config_from_json(stored)


def test_config_set_changes_one_nested_field_and_names_bad_assignments():
    from ne_jax.train.run import RunConfig

    run = RunConfig.default()  # no density gate, confidences at the base rate
    gated = cj.config_set(run, "render.kdtree.density_falloff=1.0")
    assert gated.render.kdtree.density_falloff == 1.0 and gated.replace(render=run.render) == run
    assert cj.config_set(gated, "render.kdtree.density_falloff=null") == run
    assert cj.config_set(run, "train.confidence_lr=10").train.confidence_lr == 10
    ten = cj.config_set(run, "train.confidence_lr=10")  # an integer for a float field keys as the float
    assert isinstance(ten.train.confidence_lr, float)
    assert cj.config_key(ten) == cj.config_key(run.replace(train=run.train.replace(confidence_lr=10.0)))
    both = cj.config_set(run, "render.kdtree.density_falloff=1.0", "train.confidence_lr=10")
    assert both == cj.config_set(gated, "train.confidence_lr=10") and cj.config_set(run) == run
    assert cj.config_set(run, "render.quadrature.samples_per_level=[2, 3, 5]").render.quadrature.samples_per_level \
        == (2, 3, 5)
    wide = cj.config_set(run, "render.shading.specular_widths=[64, 16]")  # a list becomes a hashable tuple
    assert wide.render.shading.specular_widths == (64, 16) and hash(wide) != hash(run)
    assert cj.config_key(wide) != cj.config_key(run)
    assert cj.config_set(wide, "render.shading.specular_widths=[48, 16]") == run
    bounds = cj.config_set(run, "init.carve.bounds=[[-1, -1, -1], [1, 1, 1]]").init.carve.bounds
    assert bounds == ((-1, -1, -1), (1, 1, 1))
    with pytest.raises(ValueError, match="expected FIELD.PATH=VALUE"):
        cj.config_set(run, "render.kdtree.density_falloff")
    with pytest.raises(ValueError, match="KDTreeConfig has no field 'falloff'.*known: .*density_falloff"):
        cj.config_set(run, "render.kdtree.falloff=1")
    with pytest.raises(ValueError, match="density_falloff"):  # the config's own check
        cj.config_set(run, "render.kdtree.density_falloff=-1")
