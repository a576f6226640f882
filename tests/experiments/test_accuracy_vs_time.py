"""Smoke test of ``experiments/accuracy_vs_time.py --study numerics`` at reduced sizes: the output
files and their schema, and monotone sanity of the numbers (no claim about timings beyond > 0)."""

from __future__ import annotations

import importlib.util
import itertools
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "experiments" / "accuracy_vs_time.py"


def _load():
    """The script as a module (registered in ``sys.modules``: its dataclasses need that)."""
    if "accuracy_vs_time" not in sys.modules:
        spec = importlib.util.spec_from_file_location("accuracy_vs_time", SCRIPT)
        mod = importlib.util.module_from_spec(spec)
        sys.modules["accuracy_vs_time"] = mod
        spec.loader.exec_module(mod)
    return sys.modules["accuracy_vs_time"]


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    avt = _load()
    out = tmp_path_factory.mktemp("accuracy_vs_time")
    assert avt.main(["--study", "numerics", "--quick", "--out-dir", str(out)]) == 0
    return avt, out, json.loads((out / "accuracy_vs_time.json").read_text())


def _finite_nonneg(xs):
    return all(isinstance(x, float) and math.isfinite(x) and x >= 0 for x in xs)


def test_files_and_schema(quick_run):
    avt, out, res = quick_run
    for name in ("accuracy_vs_time.json", "accuracy_vs_time_numerics.md", "accuracy_vs_time_quadrature.png",
                 "accuracy_vs_time_knn.png", "accuracy_vs_time_precision.png"):
        assert (out / name).stat().st_size > 0, name
    assert res["study"] == "numerics" and res["command"].endswith("--quick")
    assert {"quadrature", "knn", "precision", "wall_s", "machine", "discussion", "plots"} <= set(res)
    q = res["quadrature"]
    n_s = len(q["s_values"])
    assert set(q["rules"]) == {"hermite", "hermite_o4", "spline", "spline_natural", "trapezoid", "stochastic"}
    for rule, row in q["rules"].items():
        assert set(row["error"]) == set(avt.FIELDS)
        for kind, err in row["error"].items():
            central = avt.quadrature_error(q, rule, kind)
            assert len(central) == n_s and _finite_nonneg(central)
            assert _finite_nonneg(err["max_abs"]) and all(m >= c - 1e-15 for m, c in zip(err["max_abs"], central)
                                                         if rule != "stochastic")
        assert len(row["ms_per_1e5_segments"]) == n_s and all(t > 0 for t in row["ms_per_1e5_segments"])
    kn = res["knn"]
    assert kn["rows"] and kn["exact"]
    for r in kn["rows"]:
        assert 0.0 <= r["recall"] <= 1.0 and r["ms_per_1e6_samples"] > 0
        assert _finite_nonneg([r["diff_random_mean"], r["diff_random_max"], r["diff_smooth_mean"]])
    pr = res["precision"]
    for key in ("rgb_max_abs_diff", "rgb_mean_abs_diff", "opacity_max_abs_diff", "time_ratio_f64_over_f32"):
        assert math.isfinite(pr[key]) and pr[key] >= 0
    assert pr["lost_segments"] == [0, 0]
    md = (out / "accuracy_vs_time_numerics.md").read_text()
    assert "#### Quadrature" in md and "#### KNN" in md and "float64" in md and res["command"] in md


def test_quadrature_converges(quick_run):
    avt, _, res = quick_run
    q = res["quadrature"]
    s = q["s_values"]
    i4, i22 = s.index(4), s.index(22)
    for rule in ("hermite", "hermite_o4", "spline", "spline_natural", "trapezoid"):
        smooth = avt.quadrature_error(q, rule, "smooth")
        assert smooth[i22] < 0.1 * smooth[i4], rule  # more samples: much smaller error on a smooth field
        assert all(b <= a for a, b in itertools.pairwise(smooth)), (rule, smooth)  # never grows with s
        step = avt.quadrature_error(q, rule, "step")
        assert step[i22] < step[i4], rule
    order = {r: q["rules"][r]["order"]["smooth"] for r in q["rules"]}
    # Fitted orders (s >= 8 only: few points at quick sizes, hence the loose bounds).
    assert 1.7 < order["trapezoid"] < 2.3
    assert 2.6 < order["hermite"] < 3.4
    assert order["spline"] > 3.5 and order["hermite_o4"] > 3.3
    assert 0.8 < order["stochastic"] < 2.2
    stoch = avt.quadrature_error(q, "stochastic", "smooth")
    assert stoch[i22] < stoch[i4]


def test_knn_sanity(quick_run):
    _, _, res = quick_run
    kn = res["knn"]
    for k in {r["k"] for r in kn["rows"]}:
        rows = sorted((r for r in kn["rows"] if r["k"] == k), key=lambda r: r["candidates"])
        recall = [r["recall"] for r in rows]
        # a larger candidate set is a superset (nearest-first), so recall cannot drop
        assert all(b >= a - 1e-9 for a, b in itertools.pairwise(recall)), recall
        assert recall[-1] > 0.9
    for e in kn["exact"]:
        assert e["recall_vs_scipy"] > 0.999  # brute force agrees with scipy's exact KNN


def test_precision_sanity(quick_run):
    _, _, res = quick_run
    pr = res["precision"]
    assert pr["rgb_max_abs_diff"] < 1e-3  # float32 rendering is far below an 8-bit step
    assert pr["rgb_mean_abs_diff"] <= pr["rgb_max_abs_diff"]


def test_image_study_is_a_placeholder(capsys):
    avt = _load()
    assert avt.main(["--study", "image"]) == 2
    assert "needs a trained model: lands with issue 7 part 2" in capsys.readouterr().err


def test_fit_order_recovers_a_power_law():
    avt = _load()
    s = np.array([4, 8, 16, 32, 64])
    assert avt.fit_order(s, 3.0 * (1.0 / (s - 1)) ** 3, "hermite") == pytest.approx(3.0)
    assert avt.fit_order(s, 0.5 * (1.0 / s) ** 1.5, "stochastic") == pytest.approx(1.5)
