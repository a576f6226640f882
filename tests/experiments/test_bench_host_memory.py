"""experiments/bench_host_memory.py: each setting's child environment and the table it writes (the
measurement itself runs in experiments, not in the suite: two `default` processes per round)."""

from experiments import bench_host_memory as B
from ne_jax._host_memory import ENV, TUNABLE


def test_each_setting_starts_its_children_as_it_says(monkeypatch):
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.arena_max=2")
    monkeypatch.delenv(ENV, raising=False)
    huge, system = B._env("huge_pages"), B._env("system")
    assert huge["GLIBC_TUNABLES"] == TUNABLE and ENV not in huge
    assert "GLIBC_TUNABLES" not in system and system[ENV] == "system"  # ne-jax must not add it back


def _row(ms, faults):
    return {"ms": ms, "faults": faults, "sys_s": 0.1, "user_s": 0.3}


def test_the_table_takes_the_best_round_and_the_ratio():
    rounds = {s: [{"step": _row(ms, f), "render": _row(ms / 2, f), "compile_step_s": 15.0, "loss_last": 0.1}
                  for ms, f in rows] for s, rows in (("huge_pages", [(300.0, 3000), (280.0, 2900)]),
                                                      ("system", [(320.0, 73000), (330.0, 72000)]))}
    best = {s: {k: B._best(rounds[s], k) for k in ("step", "render")} for s in B.SETTINGS}
    assert best["huge_pages"]["step"]["ms"] == 280.0 and best["system"]["step"]["faults"] == 73000
    res = {"commit": "abc", "command": "python -m experiments.bench_host_memory", "devices": 2, "cpus": 2,
           "rounds": 2, "steps": 10, "load_average": [1.0, 1.0, 1.0], "best": best, "rounds_raw": rounds,
           "train": None, "loss_last": {s: 0.1 for s in B.SETTINGS},
           "ratio": {k: best["system"][k]["ms"] / best["huge_pages"][k]["ms"] for k in ("step", "render")}}
    md = B.to_markdown(res)
    assert "| `default` training step (2,048 rays) | huge_pages | 280.0 | 2900 |" in md
    assert "training step 1.14x, render chunk 1.14x" in md

