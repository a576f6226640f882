"""equivariance --summarize: one table of several results files' models, each cell tree carried /
rebuilt, and the worst rigid motion per model."""

from __future__ import annotations

import json

from experiments import equivariance as E


def _model(scene, carry, rebuild):
    motions = [{"motion": "rotate 2 deg about z", "kind": "rigid", "carry": carry, "rebuild": rebuild},
               {"motion": "scale by 1.1 about the centre", "kind": "scale", "carry": 10.0, "rebuild": 5.0}]
    return {"scene_dir": f"/b/{scene}", "preset": "tiny", "points": 100, "views": 2, "motions": motions}


def test_summarize_writes_one_table_of_every_model(tmp_path, monkeypatch):
    monkeypatch.setattr(E, "RESULTS", tmp_path)
    sources = []
    for scene, carry in (("cup", 120.0), ("stool", 60.25)):
        sources.append(tmp_path / f"equivariance_{scene}.json")
        sources[-1].write_text(json.dumps({"commit": "abc", "command": "cmd", "models": [_model(scene, carry, 30.0)]}))
    E.main(["--summarize", *map(str, sources), "--out", "both"])
    lines = (tmp_path / "both.md").read_text().splitlines()
    assert lines[2] == "| motion | cup (tiny) | stool (tiny) |"
    assert "| rotate 2 deg about z | 120.0 / 30.0 | 60.2 / 30.0 |" in lines
    assert "| **worst rigid motion** | 120.0 / 30.0 | 60.2 / 30.0 |" in lines  # the scaling is not rigid
    assert "- `equivariance_stool.json`: commit abc, `cmd`" in lines
