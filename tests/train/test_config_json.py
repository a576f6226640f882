"""Configs as typed JSON: round trips, keys that survive added fields, and differences by name."""

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


def test_a_field_added_after_keying_changes_the_key_only_when_set():
    """``KEY_OMITS_DEFAULT`` fields (``KDTreeConfig.density_falloff``, ``TrainConfig.confidence_lr``)
    leave every config that keeps their default under its recorded key, are written to config.json,
    and change the key when set."""
    from ne_jax.train.run import RunConfig

    run = RunConfig.default()  # keeps both at their defaults
    assert "density_falloff" in cj.config_to_json(run)["render"]["kdtree"]
    assert "density_falloff" not in json.dumps(cj.config_to_json(run, _for_key=True))
    gated = run.replace(render=run.render.replace(kdtree=run.render.kdtree.replace(density_falloff=1.0)))
    faster = run.replace(train=run.train.replace(confidence_lr=10.0))
    assert len({cj.config_key(run), cj.config_key(gated), cj.config_key(faster)}) == 3
    assert cj.config_from_json(json.loads(json.dumps(cj.config_to_json(gated)))) == gated


def test_a_config_with_buffer_sizes_among_its_settings_reads_back():
    """config.json files that stored the buffer sizes in the tree and render configs read back with
    them moved to ``RunConfig.capacities`` (and are no difference to the same run written now)."""
    from ne_jax.train.run import RunConfig

    run = RunConfig.default()
    old = json.loads(json.dumps(cj.config_to_json(run)))
    del old["capacities"]
    old["render"]["tree"] = old["render"].pop("kdtree")  # the field's older name too
    old["render"]["tree"].update(frontier_capacity=64, first_pass_frontier=16, retry_share=0.25, max_segments=32)
    old["render"]["segments_per_ray"] = 8.0
    back = cj.config_from_json(old)
    assert back == run.replace(capacities=run.capacities.replace(segments_per_ray=8.0))
    assert cj.config_diff(old, cj.config_to_json(run)) == []
    render_only = cj.config_from_json(old["render"])  # not a run: the sizes are dropped
    assert render_only == run.render


def test_a_field_added_later_at_its_default_is_no_difference():
    """A config written before a field existed (e.g. ``TrainConfig.train_ist``) equals today's when
    today's value is the default; a non-default value, or a changed field, is still a difference."""
    expected = cj.config_to_json(TCFG)
    old = json.loads(json.dumps(expected))
    del old["train_ist"]
    del old["loss"]["ist_orthogonality"]
    assert cj.config_diff(old, expected) == []
    changed = cj.config_to_json(TCFG.replace(train_ist=True))
    assert cj.config_diff(old, changed) == ["train_ist (missing in checkpoint; run has True)"]
    old["lr"] = 123.0
    assert len(cj.config_diff(old, expected)) == 1


def test_a_config_stored_under_a_moved_type_name_reads_back_and_resumes():
    """A run directory written while ``RunConfig`` lived in ``ne_jax.train.loop`` still loads, and its
    config is no difference from today's (so the run resumes)."""
    from ne_jax.train.run import RunConfig

    run = RunConfig.tiny()
    stored = json.loads(json.dumps(cj.config_to_json(run)).replace("ne_jax.train.run:", "ne_jax.train.loop:")
                        .replace("ne_jax.pointcloud.rounds:RoundConfig", "ne_jax.pointcloud.optimise:PointOptConfig")
                        .replace('"rounds":', '"points":').replace('"round_epochs":', '"point_rounds":')
                        .replace('"background_model":', '"background":'))
    assert stored["__type__"] == "ne_jax.train.loop:RunConfig"
    assert stored["points"]["__type__"] == "ne_jax.pointcloud.optimise:PointOptConfig"
    assert "point_rounds" in stored and "round_epochs" not in stored
    assert stored["render"]["shading"]["effects"]["background"] == "constant"
    assert cj.config_from_json(stored) == run
    assert cj.config_diff(stored, cj.config_to_json(run)) == []
    assert cj.config_diff(stored, cj.config_to_json(run.replace(seed=1))) == ["seed: checkpoint 0, run 1"]


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
    wide = cj.config_set(run, "render.shading.diffuse_widths=[64, 16]")  # a None field takes a tuple too
    assert wide.render.shading.diffuse_widths == (64, 16) and hash(wide) != hash(run)
    assert cj.config_key(wide) != cj.config_key(run)
    assert cj.config_set(wide, "render.shading.diffuse_widths=null") == run
    bounds = cj.config_set(run, "init.carve.bounds=[[-1, -1, -1], [1, 1, 1]]").init.carve.bounds
    assert bounds == ((-1, -1, -1), (1, 1, 1))
    with pytest.raises(ValueError, match="expected FIELD.PATH=VALUE"):
        cj.config_set(run, "render.kdtree.density_falloff")
    with pytest.raises(ValueError, match="KDTreeConfig has no field 'falloff'.*known: .*density_falloff"):
        cj.config_set(run, "render.kdtree.falloff=1")
    with pytest.raises(ValueError, match="density_falloff"):  # the config's own check
        cj.config_set(run, "render.kdtree.density_falloff=-1")
