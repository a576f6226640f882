"""The see-through study walks the see-through pixels' rays again and renders other box margins."""

from __future__ import annotations

import json

import pytest

from experiments import see_through
from ne_jax.benchmark.generate import generate_scene
from ne_jax.train.loop import train

from tests.mini_presets import mini_benchmark, mini_run


@pytest.mark.slow  # a study run end to end: -m slow
def test_study_reports_the_crossings_and_each_margin(tmp_path, monkeypatch):
    bench = mini_benchmark(test_views=2)
    generate_scene("glossy", bench, tmp_path / "bench", seed=0, edits=[])
    train(mini_run(epochs=1, steps_per_epoch=2, round_epochs=(1, 0)), tmp_path / "bench" / "glossy", tmp_path / "run",
          progress=False, log=lambda s: None)
    monkeypatch.setattr(see_through, "RESULTS", tmp_path / "out")
    see_through.main(["--run", str(tmp_path / "run"), str(tmp_path / "bench" / "glossy"), "--views", "0", "1",
                      "--margins", "2.0", "--out", "t"])
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


def test_views_out_of_range_are_named(tmp_path):
    generate_scene("glossy", mini_benchmark(), tmp_path / "bench", seed=0, edits=[])
    train(mini_run(epochs=1, steps_per_epoch=1, round_epochs=(1, 0)), tmp_path / "bench" / "glossy", tmp_path / "run",
          progress=False, log=lambda s: None)
    with pytest.raises(SystemExit, match=r"--views: expected test views 0\.\.0 .* found \[3\]"):
        see_through.main(["--run", str(tmp_path / "run"), str(tmp_path / "bench" / "glossy"), "--views", "3",
                          "--out", "t"])
