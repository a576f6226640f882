"""Configs as typed JSON: round trips, keys that survive added fields, and differences by name."""

import json

import pytest

import ne_jax.config_json as cj

from .test_checkpoint import SMALL_RCFG, SMALL_TCFG
from .test_step import RCFG, TCFG


def test_configs_round_trip_with_types():
    from ne_jax.geometry.kdtree import KDTreeConfig
    from ne_jax.render.renderer import RenderConfig

    paper = RenderConfig(tree=KDTreeConfig(depth=21, max_segments=64), segments_per_ray=None)
    for cfg in (SMALL_TCFG, SMALL_RCFG, paper,
                RCFG.with_effects(background="sphere")):
        data = json.loads(json.dumps(cj.config_to_json(cfg)))
        back = cj.config_from_json(data)
        assert back == cfg and type(back) is type(cfg)
    with pytest.raises(cj.ConfigError, match="expected an ne_jax dataclass"):
        cj.config_from_json({"__type__": "os:system", "command": "true"})


def test_fields_added_later_keep_old_keys():
    """A field flagged ADDED_LATER is left out of the key at its default (keys of runs made before it
    existed stay valid) and counts once set; config.json always holds it."""
    import dataclasses
    import hashlib

    from ne_jax.geometry.kdtree import KDTreeConfig
    from ne_jax.train.run import RunConfig

    added = [f.name for f in dataclasses.fields(KDTreeConfig) if f.metadata.get(cj.ADDED_LATER)]
    assert added == ["first_pass_frontier", "retry_share"]
    run = RunConfig.tiny()  # walks in one pass: both fields at their defaults
    assert run.render.tree.first_pass_frontier is None
    stripped = cj.config_to_json(run)
    for name in added:
        del stripped["render"]["tree"][name]
    old_key = hashlib.sha256(json.dumps(stripped, sort_keys=True).encode()).hexdigest()[:12]
    assert cj.config_key(run) == old_key
    assert "first_pass_frontier" in cj.config_to_json(run)["render"]["tree"]
    two_pass = run.replace(render=run.render.replace(tree=run.render.tree.replace(first_pass_frontier=8)))
    assert cj.config_key(two_pass) != old_key
    assert cj.config_from_json(json.loads(json.dumps(stripped))) == run  # an old config.json reads back the same


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
    stored = json.loads(json.dumps(cj.config_to_json(run)).replace("ne_jax.train.run:", "ne_jax.train.loop:"))
    assert stored["__type__"] == "ne_jax.train.loop:RunConfig"
    assert cj.config_from_json(stored) == run
    assert cj.config_diff(stored, cj.config_to_json(run)) == []
    assert cj.config_diff(stored, cj.config_to_json(run.replace(seed=1))) == ["seed: checkpoint 0, run 1"]
