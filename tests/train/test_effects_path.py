"""Undeclared effects cost nothing through train -> edit -> eval, read from what XLA compiles.

Every module compiled in a stage is dumped (``jax_dump_ir_to``: the StableHLO handed to the
compiler, with its locations) and read for the specular branch (ops under its Flax modules, ops of
the IDE and of the reflection, its parameters as arguments) and for the per-point arrays a module
reads. ``jit`` removes ops whose results are unused and then the arguments no op reads, so an array
is read, and costs something, exactly when it is still an argument. The same stages with the effect
declared must show each of them, so every check can fail."""

from __future__ import annotations

import contextlib
import dataclasses
import re
from pathlib import Path

import jax
import numpy as np
import pytest

from ne_jax.benchmark.edits import benchmark_edit
from ne_jax.benchmark.generate import generate_scene
from ne_jax.data.nerf_synthetic import load_split
from ne_jax.edit.model import edit_model
from ne_jax.eval import evaluate_model
from ne_jax.train.effects import declare_effects
from ne_jax.train.loop import train

from tests.mini_presets import MINI_CAPS, mini_benchmark, short_run

SPECULAR_MODULES = ("specular", "tint", "roughness", "bottleneck")
"""Submodules of the colour model that only the specular branch has."""
SPECULAR_FUNCTIONS = ("integrated_dir_enc", "reflect")
"""Functions whose ops only the specular branch traces: the IDE and the reflected direction."""
_DUMP_FLAGS = {"jax_dump_ir_to": None, "jax_dump_ir_modes": "stablehlo", "jax_include_debug_info_in_dumps": True,
               "jax_include_full_tracebacks_in_locations": True, "jax_traceback_in_locations_limit": 100}


def _flag(name: str):
    try:
        return jax.config.read(name)
    except AttributeError:  # a flag with a context manager is read as an attribute
        return getattr(jax.config, name)


@dataclasses.dataclass
class Module:
    """One compiled module: file name, argument names (pytree paths such as ``scene.points.ist``,
    ``params['shader']['tint']['kernel']``) and every location (name stacks, traceback frames)."""

    name: str
    args: list[str]
    locations: list[str]

    @classmethod
    def read(cls, path: Path) -> Module:
        text = path.read_text()
        main = re.search(r"func\.func public @main\((.*?)\) -> ", text)
        args = re.findall(r'loc\("([^"]*)"\)', main.group(1)) if main else []
        return cls(path.name, args, re.findall(r"^#loc\d+ = loc\((.*)\)$", text, flags=re.M))

    def in_scope(self, *path: str) -> bool:
        """Whether an op runs under the Flax module path ``path``, also inside autodiff's
        ``jvp(...)`` / ``transpose(...)`` wrappers of a name."""
        pattern = "/".join(rf"(?:\w+\()*{re.escape(p)}\)*" for p in path)
        return any(re.search(rf'(?:^"|/){pattern}/', loc) for loc in self.locations)

    def traces(self, function: str) -> bool:
        """Whether an op's traceback passes through the Python function ``function``."""
        return any(loc.startswith(f'"{function}"(') for loc in self.locations)

    def reads(self, array: str) -> bool:
        """Whether the point scene's ``array`` (``ist``, ``normal``) is read: still an argument."""
        return f"scene.points.{array}" in self.args

    @property
    def shades(self) -> bool:
        """Whether the module evaluates the colour model (its trunk runs for every shaded segment)."""
        return self.in_scope("SegmentShader", "trunk")

    def specular(self) -> list[str]:
        """What of the specular branch the module holds (empty: nothing)."""
        found = [f"ops of {m}" for m in SPECULAR_MODULES if self.in_scope("SegmentShader", m)]
        found += [f"ops of {f}()" for f in SPECULAR_FUNCTIONS if self.traces(f)]
        return found + [f"argument {a}" for a in self.args if any(f"['{m}']" in a for m in SPECULAR_MODULES)]


@contextlib.contextmanager
def compiled(folder: Path):
    """Dump every module XLA compiles inside the block into ``folder``; yields a list that holds
    their :class:`Module` s after the block."""
    old = {name: _flag(name) for name in _DUMP_FLAGS}
    modules: list[Module] = []
    for name, value in _DUMP_FLAGS.items():
        jax.config.update(name, str(folder) if value is None else value)
    try:
        yield modules
    finally:
        for name, value in old.items():
            jax.config.update(name, value)
    modules.extend(Module.read(p) for p in sorted(folder.glob("*.mlir")))


@pytest.fixture(scope="module")
def stages(tmp_path_factory):
    """A glossy scene (its ``scene.json`` declares specular on) trained with ``specular=off`` and
    with the scene's declaration, each edited by the rigid ``tilt_ring`` with the IST and
    evaluated: ``{(spec, stage): [Module]}`` for the stages ``train``, ``eval`` (the unedited
    model; ``scene`` only) and ``edit_eval`` (the edit and the edited model's evaluation), and
    ``{(spec, "models"): (model, edited, report)}``.

    IDE degree 2 (fewer ops to compile) also makes each stage's render config this module's own,
    so no shading module is served from a cache filled by another test: each stage compiles its
    own (the tests check that one was seen). A traversal frontier of 32 nodes from the start: the
    edited cloud's render would grow 16 to 32 and compile its render again."""
    root = tmp_path_factory.mktemp("effects_path")
    generate_scene("glossy", mini_benchmark(resolution=16, train_views=4, surface_samples=800), root / "bench", 0,
                   edits=("tilt_ring",))
    scene = root / "bench" / "glossy"
    base = short_run(steps_per_epoch=2, capacities=MINI_CAPS.replace(frontier=32))
    base = base.replace(render=base.render.replace(shading=dataclasses.replace(base.render.shading, ide_degree=2)))
    edit, truth = benchmark_edit(scene, "tilt_ring")
    out = {}
    for spec in ("specular=off", "scene"):
        run = base.replace(render=declare_effects(base.render, spec, scene)[0])
        dump = root / "dumps" / spec
        with compiled(dump / "train") as out[spec, "train"]:
            model = train(run, scene, root / "runs" / spec, progress=False, log=lambda s: None)
        if spec == "scene":
            with compiled(dump / "eval") as out[spec, "eval"]:
                evaluate_model(model, load_split(scene, "test"), progress=False, lpips_net=None)
        with compiled(dump / "edit_eval") as out[spec, "edit_eval"]:
            edited, _ = edit_model(model, edit, ist=True, scene_dir=truth)
            report, _ = evaluate_model(edited, load_split(truth, "test"), progress=False, lpips_net=None)
        out[spec, "models"] = (model, edited, report)
    return out


def _shading(stages, spec, stage) -> list[Module]:
    found = [m for m in stages[spec, stage] if m.shades]
    assert found, f"{spec} {stage}: no compiled module shades segments (nothing was checked)"
    return found


@pytest.mark.parametrize("stage", ["train", "edit_eval"])
def test_undeclared_specular_is_not_compiled(stages, stage):
    _shading(stages, "specular=off", stage)
    for m in stages["specular=off", stage]:
        assert not m.specular(), f"specular off, yet {stage} compiled {m.name} with {m.specular()}"
    expected = [f"ops of {n}" for n in SPECULAR_MODULES] + [f"ops of {f}()" for f in SPECULAR_FUNCTIONS]
    for m in _shading(stages, "scene", stage):  # declared: each module that shades holds all of it
        found = m.specular()
        assert set(expected) <= set(found), f"specular on, yet {m.name} lacks {set(expected) - set(found)}"
        assert any(w.startswith("argument") for w in found)


def test_undeclared_specular_has_no_parameters_through_the_path(stages):
    for spec, present in (("specular=off", False), ("scene", True)):
        model, edited, report = stages[spec, "models"]
        assert model.run.render.shading.effects.specular == edited.run.render.shading.effects.specular == present
        for m in (model, edited):
            keys = set(m.params["shader"])
            assert set(SPECULAR_MODULES) <= keys if present else not set(SPECULAR_MODULES) & keys, sorted(keys)
        assert np.isfinite(report["psnr"])


def test_rendering_reads_the_normals_only_for_specular(stages):
    """Only the specular branch reflects about point normals (the training losses read them
    whatever the effects): the edited model's evaluation reads them only with specular on."""
    assert not any(m.reads("normal") for m in _shading(stages, "specular=off", "edit_eval"))
    assert all(m.reads("normal") for m in _shading(stages, "scene", "edit_eval"))


def test_the_ist_is_read_only_where_declared_and_used(stages):
    """An unedited model does not declare the IST: neither its training nor its evaluation reads
    the IST arrays. The edited model declares it and reads it; with specular off the colour does not
    depend on the view, so there is nothing to redirect and the declared IST is not read either."""
    model, edited, _ = stages["scene", "models"]
    assert not model.run.render.shading.effects.ist and edited.run.render.shading.effects.ist
    for spec, stage in (("specular=off", "train"), ("scene", "train"), ("scene", "eval")):
        assert not any(m.reads("ist") for m in _shading(stages, spec, stage)), (spec, stage)
    assert all(m.reads("ist") for m in _shading(stages, "scene", "edit_eval"))
    assert not any(m.reads("ist") for m in _shading(stages, "specular=off", "edit_eval"))
