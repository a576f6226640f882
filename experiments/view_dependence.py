"""How much of a trained model's accuracy is view dependence: its test views rendered as trained, and
again with every segment's view direction replaced by its reflection normal turned around
(``-n``: the reflected direction is then ``n`` itself), so the colour model keeps its specular
branch but can no longer vary with the camera. On a scene whose ground truth is view independent
(``blocks`` is Lambertian) a large drop says the model uses view dependence for something else:
parallax where its cloud is off the surface.

    python -m experiments.view_dependence --run LABEL RUN_DIR [--run ...] --out view_dependence_default

Only models with the specular effect (and point normals) are measured; a model without it has no
view dependence to remove. Writes ``experiments/results/<out>.{json,md}``.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from experiments import common
from ne_jax.config_json import config_key
from ne_jax.data.nerf_synthetic import load_split
from ne_jax.eval import evaluate_model
from ne_jax.numerics import safe_normalize
from ne_jax.render.shading import ShadingConfig, background_color, shade
from ne_jax.train.model import load_trained

RESULTS = Path(__file__).resolve().parent / "results"


@dataclasses.dataclass(frozen=True)
class ViewFromNormal:
    """Stands in for ``RenderConfig.shading`` (like morphing's ``BlendedShading``): ``inner``'s
    colour model, shading every segment as if seen along its point normal."""

    inner: ShadingConfig

    @property
    def effects(self):
        return self.inner.effects

    @property
    def feature_dim(self) -> int:
        return self.inner.feature_dim

    def shade(self, params, feature, normal, view_dir, ist=None, pred_normal_mix=None):
        return shade(self.inner, params, feature, normal, -safe_normalize(normal), ist, pred_normal_mix)

    def background_color(self, params, origin, direction, constant=None):
        return background_color(self.inner, params, origin, direction, constant)


def measure(label: str, run_dir: Path) -> dict:
    model = load_trained(run_dir)
    fx = model.run.render.shading.effects
    row = {"label": label, "run": str(run_dir), "config_key": config_key(model.run),
           "pixel_samples": model.run.render.pixel_samples, "specular": bool(fx.specular)}
    if not (fx.specular and fx.uses_point_normals):
        return {**row, "psnr": None, "psnr_view_from_normal": None}
    split = load_split(model.scene_dir, "test")
    psnr = evaluate_model(model, split, progress=False, lpips_net=None)[0]["psnr"]
    fixed = model.replace(run=model.run.replace(render=model.run.render.replace(shading=ViewFromNormal(
        model.run.render.shading))))
    psnr_fixed = evaluate_model(fixed, split, progress=False, lpips_net=None)[0]["psnr"]
    print(f"{label}: {psnr:.2f} dB as trained, {psnr_fixed:.2f} dB seen along the normals", flush=True)
    return {**row, "views": split.num_views, "psnr": round(psnr, 2), "psnr_view_from_normal": round(psnr_fixed, 2),
            "drop_db": round(psnr - psnr_fixed, 2)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", nargs=2, action="append", required=True, metavar=("LABEL", "RUN_DIR"))
    ap.add_argument("--out", default="view_dependence")
    args = ap.parse_args(argv)
    rows = [measure(label, Path(d)) for label, d in args.run]
    cmd = "python -m experiments.view_dependence " + " ".join(f"--run {a} {b}" for a, b in args.run) + \
        f" --out {args.out}"
    report = {"command": cmd, "commit": common.commit(), "rows": rows}
    lines = [f"Test PSNR as trained and with each segment seen along its point normal (no view dependence); "
             f"commit {report['commit']}; `{cmd}`.", "",
             "| model | config key | rays per pixel | PSNR as trained | seen along the normals | drop (dB) |",
             "|---|---|---:|---:|---:|---:|"]
    for r in rows:
        if r["psnr"] is None:
            lines.append(f"| {r['label']} | {r['config_key']} | {r['pixel_samples']}x{r['pixel_samples']} | "
                         "specular off: nothing to remove | | |")
        else:
            lines.append(f"| {r['label']} | {r['config_key']} | {r['pixel_samples']}x{r['pixel_samples']} | "
                         f"{r['psnr']:.2f} | {r['psnr_view_from_normal']:.2f} | {r['drop_db']:.2f} |")
    common.write_results(RESULTS, args.out, report, "\n".join(lines) + "\n")


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()
