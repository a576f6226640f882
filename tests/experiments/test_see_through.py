"""The see-through study walks the see-through pixels' rays again and renders other box margins.

The default tests run the command line with the model's measurements stood in for (no training, no
rendering): its arguments, one row per margin and the JSON and table it writes. The study on a
trained model runs with ``-m slow``."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest

from experiments import see_through
from ne_jax.benchmark.generate import generate_scene
from ne_jax.config_json import config_key
from ne_jax.train.loop import train

from tests.mini_presets import mini_benchmark, mini_run


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 24-px glossy scene with two test views (no edits)."""
    root = tmp_path_factory.mktemp("see_through")
    generate_scene("glossy", mini_benchmark(test_views=2), root / "bench", seed=0, edits=[])
    return root / "bench" / "glossy"


def _stand_in_model(monkeypatch):
    """A model that only carries its run config, returned by ``load_trained`` for any run directory."""
    model = SimpleNamespace(run=mini_run())
    monkeypatch.setattr("ne_jax.train.model.load_trained", lambda run_dir: model)
    return model


@pytest.mark.slow  # a study run end to end: -m slow
def test_study_reports_the_crossings_and_each_margin(scene, tmp_path, monkeypatch):
    train(mini_run(epochs=1, steps_per_epoch=2, round_epochs=(1, 0)), scene, tmp_path / "run",
          progress=False, log=lambda s: None)
    monkeypatch.setattr(see_through, "RESULTS", tmp_path / "out")
    see_through.main(["--run", str(tmp_path / "run"), str(scene), "--views", "0", "1", "--margins", "2.0",
                      "--out", "t"])
    res = json.loads((tmp_path / "out" / "see_through_t.json").read_text())
    own, wider = res["margins"]
    assert own["margin_factor"] == 1.0 and wider["margin_factor"] == 2.0
    # wider boxes: at least as many segments on an object ray
    assert wider["segments_per_object_ray"] >= own["segments_per_object_ray"] > 0
    c = res["crossing"]
    assert 0 <= c["with_a_segment_at_the_surface"] <= c["see_through_pixels"]
    assert len(c["ordinary_pixels_to_nearest_point_spacings_quartiles"]) == 3
    md = (tmp_path / "out" / "see_through_t.md").read_text()
    assert "| 1 | trained |" in md and "| 2 | rebuilt |" in md


def test_views_out_of_range_are_named(scene, monkeypatch):
    _stand_in_model(monkeypatch)
    with pytest.raises(SystemExit, match=r"--views: expected test views 0\.\.1 .* found \[3\]"):
        see_through.main(["--run", "RUN", str(scene), "--views", "3", "--out", "t"])


def test_one_row_per_margin_and_the_crossing_are_written(scene, tmp_path, monkeypatch):
    """The own tree's row first, then one per ``--margins`` entry, each measured on the views asked for;
    the crossing report from the own tree's depths and labels; both in the JSON and the table."""
    model = _stand_in_model(monkeypatch)
    monkeypatch.setattr(see_through, "RESULTS", tmp_path / "out")
    asked = []

    def margin_row(m, split, views, margin):
        assert m is model and views == [0, 1] and split.num_views == 2
        asked.append(margin)
        factor = 1.0 if margin is None else margin
        row = {"margin_factor": factor, "psnr": 20.0 + factor, "psnr_per_view": [20.0, 21.0],
               "see_through_pixels": 4, "see_through_error_share": 0.25,
               "segments_per_object_ray": 2.0 * factor, "seconds_per_image": 0.5}
        return row, {"depths of": factor}, {"labels of": factor}

    def crossing_report(m, split, views, depths, labels):
        assert m is model and views == [0, 1]
        assert depths == {"depths of": 1.0} and labels == {"labels of": 1.0}  # the own tree's
        return {"see_through_pixels": 7, "with_a_segment_at_the_surface": 3,
                "crossing_to_nearest_point_spacings_quartiles": [0.5, 1.0, 1.5],
                "ordinary_pixels_to_nearest_point_spacings_quartiles": [0.1, 0.2, 0.3], "spacing": 0.01}

    monkeypatch.setattr(see_through, "margin_row", margin_row)
    monkeypatch.setattr(see_through, "crossing_report", crossing_report)
    argv = ["--run", "RUN", str(scene), "--views", "0", "1", "--margins", "1.5", "2.0", "--out", "t"]
    see_through.main(argv)
    assert asked == [None, 1.5, 2.0]
    res = json.loads((tmp_path / "out" / "see_through_t.json").read_text())
    assert [r["margin_factor"] for r in res["margins"]] == [1.0, 1.5, 2.0]
    assert res["crossing"]["with_a_segment_at_the_surface"] == 3 and res["views"] == [0, 1]
    assert res["config_key"] == config_key(model.run) and res["run"] == "RUN" and res["scene_dir"] == str(scene)
    assert res["command"].endswith("--margins 1.5 2.0 --out t") and res["seconds"] >= 0
    md = (tmp_path / "out" / "see_through_t.md").read_text()
    assert "Of 7 see-through pixels, 3 have a segment" in md and "[0.5, 1.0, 1.5]" in md
    assert "| 1 | trained | 21.00 | 4 | 25% | 2.0 | 0.50 |" in md
    assert "| 1.5 | rebuilt |" in md and "| 2 | rebuilt |" in md
