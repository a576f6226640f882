"""RunConfig presets: the serialised presets are pinned (cached runs are matched by their JSON and
keys), and the learning-rate schedule spans the run however its length is set (its length is the
run's, not a setting)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from ne_jax.cli import build_parser
from ne_jax.config_json import config_key, config_to_json
from ne_jax.train.run import PRESETS, RunConfig, load_run_config
from ne_jax.train.state import LR_FINAL_FRACTION, TrainConfig

GOLDEN = Path(__file__).parent / "golden"
"""``<preset>.config.json``: each preset's ``config.json`` as ``train`` writes it; ``keys.json``: their
:func:`config_key` (as recorded in ``experiments/results``)."""


@pytest.mark.parametrize("name", ["tiny", "default", "paper"])
def test_the_presets_serialize_byte_for_byte_as_pinned(name):
    cfg = PRESETS[name]()
    text = json.dumps(config_to_json(cfg), indent=2) + "\n"
    assert text == (GOLDEN / f"{name}.config.json").read_text(encoding="utf-8")
    assert config_key(cfg) == json.loads((GOLDEN / "keys.json").read_text())[name]
    _spans(cfg, cfg.epochs, cfg.steps_per_epoch)


def _spans(run: RunConfig, epochs: int, steps: int) -> None:
    assert (run.epochs, run.steps_per_epoch) == (epochs, steps)
    assert run.total_steps == epochs * steps
    lr = run.train.schedule(run.total_steps)
    floor = run.train.lr * LR_FINAL_FRACTION
    assert float(lr(run.total_steps - 1)) > floor  # still decaying on the last step
    assert float(lr(run.total_steps)) == pytest.approx(floor)


@pytest.mark.parametrize("preset", ["tiny", "default", "paper"])
def test_preset_keyword_arguments_set_the_length_the_schedule_spans(preset):
    make = getattr(RunConfig, preset)
    base = make()
    _spans(make(epochs=10), 10, base.steps_per_epoch)
    _spans(make(steps_per_epoch=7), base.epochs, 7)
    _spans(make(epochs=2, steps_per_epoch=3, seed=4), 2, 3)


def test_replace_changes_the_length_the_schedule_spans():
    tiny = RunConfig.tiny()
    _spans(tiny.replace(epochs=10), 10, 125)
    _spans(tiny.replace(steps_per_epoch=40).replace(epochs=3), 3, 40)
    _spans(tiny.replace(epochs=4, train=tiny.train.replace(lr=1e-3)), 4, 125)
    assert tiny.replace(epochs=10).train == tiny.train  # the length is the run's, not the TrainConfig's


def test_with_schedule_sets_the_length():
    _spans(RunConfig.tiny().with_schedule(epochs=3), 3, 125)
    _spans(RunConfig.default().with_schedule(steps_per_epoch=20), 12, 20)
    assert RunConfig.tiny().with_schedule(2, 5) == RunConfig.tiny().replace(epochs=2, steps_per_epoch=5)
    _spans(RunConfig(epochs=2, steps_per_epoch=5), 2, 5)  # a hand-built config spans its run too


def test_the_schedule_length_is_not_a_setting(tmp_path):
    with pytest.raises(TypeError, match="total_steps"):
        TrainConfig(total_steps=300)
    with pytest.raises(ValueError, match="total_steps"):
        TrainConfig().schedule(0)
    # a config.json written when it was one is refused, naming the field (no upgrade)
    data = config_to_json(RunConfig.tiny())
    data["train"]["total_steps"] = 750
    (tmp_path / "config.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"TrainConfig'.*no field\(s\) \['total_steps'\]"):
        load_run_config(tmp_path)


@pytest.mark.parametrize("argv, epochs, steps", [
    (["--epochs", "10"], 10, 125),
    (["--steps-per-epoch", "9"], 6, 9),
    (["--epochs", "2", "--steps-per-epoch", "9"], 2, 9),
])
def test_the_cli_length_options_fit_the_schedule(argv, epochs, steps):
    from ne_jax.cli import _run_config

    args = build_parser().parse_args(["train", "scene", "--out", "run", "--preset", "tiny", *argv])
    _spans(_run_config(args), epochs, steps)


def test_the_cli_set_option_changes_one_field_and_names_bad_ones():
    from ne_jax.cli import _run_config

    def run_of(*argv):
        return _run_config(build_parser().parse_args(["train", "scene", "--out", "run", "--preset", "tiny", *argv]))

    gated = run_of("--set", "render.kdtree.density_falloff=1.0", "--set", "train.confidence_lr=10")
    assert gated.render.kdtree.density_falloff == 1.0 and gated.train.confidence_lr == 10
    assert gated.total_steps == RunConfig.tiny().total_steps
    with pytest.raises(ValueError, match="RunConfig has no field 'renderer'"):
        run_of("--set", "renderer.chunk=4")


def test_the_cli_takes_the_initial_ply_from_ply_or_set_and_names_a_missing_one():
    from ne_jax.cli import _run_config

    def run_of(*argv):
        return _run_config(build_parser().parse_args(["train", "scene", "--out", "run", "--preset", "tiny", *argv]))

    assert run_of("--init", "ply", "--ply", "a.ply").init.ply_path == "a.ply"
    assert run_of("--init", "ply", "--set", "init.ply_path=b.ply").init.ply_path == "b.ply"
    assert run_of("--init", "ply", "--set", 'init.ply_path="c d.ply"').init.ply_path == "c d.ply"  # as JSON
    with pytest.raises(ValueError, match="--init ply: expected the initial cloud as --ply FILE"):
        run_of("--init", "ply")
    with pytest.raises(ValueError, match="--ply: given with --init 'sfm'"):
        run_of("--init", "sfm", "--ply", "a.ply")
