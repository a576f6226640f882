"""The jitted training step: render a batch, the losses, Adam, and a guard against non-finite values.

``step_fn = make_train_step(cfg, render_cfg, total_steps=run.total_steps)``;
``state, metrics = step_fn(state, scene, batch)``. It compiles once per ``(cfg, render_cfg,
total_steps)`` and per shape of its inputs (fixed: the batch size is static in the sampler, the
cloud's capacity in the scene), so a training loop never recompiles.

Gradients: one forward pass through :func:`~ne_jax.render.renderer.render_rays_with_aux` and one
VJP of it, split in two stages: the render (trainables -> per-ray colours and per-segment
quantities) and the losses (those -> the terms). The loss stage is cheap, so each term also gets
its own gradient w.r.t. the render's outputs; the total gradient is the loss VJP with the weights
as cotangent, pulled back once through the render.

Non-finite guard: the step writes nothing when a loss term, a gradient or the updated trainables
hold a NaN or Inf; it returns the old state with ``skipped + 1`` (``step`` unchanged). The metrics
say what went bad: ``finite/<term>`` is False when the term's value, or its gradient w.r.t. the
render's outputs (and the confidences it reads directly), is non-finite; ``finite/grad`` is False
when the gradient w.r.t. the trainables is -- with every ``finite/<term>`` True, the NaN arose in
the render's backward pass, which all rendered terms share (it cannot be attributed to one term
without a backward pass per term); ``finite/update`` is False when the updated trainables are not
finite (e.g. a parameter that was already NaN, which has a zero gradient where it is unused).

Runtime checks (``render_cfg.checks``, :mod:`ne_jax.checks`): the step runs under ``checkify`` and
the first non-finite value raises :class:`~ne_jax.checks.NonFiniteError` naming its stage: the
render's (``traversal``, ``interpolation``, ``shading``, ``compositing``), then ``loss/<term>``
(the term or its gradient w.r.t. the render's outputs), ``backward`` (the gradient w.r.t. the
trainables), ``update`` (the updated trainables). Off (default): nothing traced, the guard above.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import optax
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from ne_jax.checks import checked, stage_check
from ne_jax.devices import RAYS, default_mesh, even_mesh, shard_rays
from ne_jax.render.renderer import PointScene, RenderConfig, SegmentAux, render_rays_with_aux
from ne_jax.train.losses import loss_terms
from ne_jax.train.sampler import Batch
from ne_jax.train.state import TrainConfig, TrainState


def _all_finite(tree) -> jax.Array:
    leaves = jax.tree_util.tree_leaves(tree)
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves])) if leaves else jnp.bool_(True)


def make_train_step(cfg: TrainConfig, render_cfg: RenderConfig, mesh: Mesh | None = None, *, total_steps: int):
    """The jitted ``step_fn(state, scene, batch) -> (state, metrics)`` of a run of ``total_steps``
    steps (the length of the learning-rate schedule, :meth:`TrainConfig.schedule`), the batch's
    rays split over ``mesh`` (default :func:`~ne_jax.devices.default_mesh`; a batch that does not
    split evenly over it runs on the largest leading part it does split over, :func:`~ne_jax.devices.even_mesh`):
    each device renders its rays and differentiates its share of the losses, the terms and
    gradients are averaged over the devices (``pmean``), and the replicated Adam update follows.

    Args (of ``step_fn``):
        state: :class:`~ne_jax.train.state.TrainState`.
        scene: :class:`~ne_jax.render.renderer.PointScene` with the fixed arrays (positions,
            normals, ISTs, ``alive``) and the tree; its ``feature``/``conf_logit`` are ignored.
        batch: :class:`~ne_jax.train.sampler.Batch` (``[B]`` rays, targets ``[B, 4]``; with
            ``render_cfg.pixel_samples = n > 1``, ``B / n**2`` pixels of ``n * n`` consecutive rays,
            and the photometric loss compares each pixel's mean colour with its target).

    Metrics (scalars): ``loss/<term>`` (unweighted), ``loss/total`` (weighted), ``finite/<term>``,
    ``finite/grad``, ``finite/update``, ``ok`` (the step was applied), ``psnr`` (of the batch MSE), ``lr`` (the rate
    used), ``grad_norm``, ``opacity`` (mean over the batch), ``lost/frontier``, ``lost/slots``,
    ``lost/packing``, ``lost/emitted`` (the batch's :class:`~ne_jax.geometry.capacity.Lost`, summed;
    the first three should be 0), ``lost/max_emitted`` and ``lost/rays``.
    """
    mesh = default_mesh() if mesh is None else mesh
    if mesh.devices.size == 1 or render_cfg.checks:
        return _make_train_step(cfg, render_cfg, mesh, total_steps)
    steps: dict = {}  # one step per mesh the batch sizes split over (one, for a fixed batch size)

    def step_on_even_mesh(state: TrainState, scene: PointScene, batch: Batch):
        sub = even_mesh(batch.rays.num_rays // render_cfg.pixel_samples ** 2, mesh)  # whole pixels per device
        if sub not in steps:
            steps[sub] = _make_train_step(cfg, render_cfg, sub, total_steps)
        return steps[sub](state, scene, batch)

    return step_on_even_mesh


def _make_train_step(cfg: TrainConfig, render_cfg: RenderConfig, mesh: Mesh, total_steps: int):
    """:func:`make_train_step` on ``mesh``, the batch size a multiple of its size."""
    weights = cfg.loss.weights()
    optimizer = cfg.optimizer(total_steps)
    schedule = cfg.schedule(total_steps)
    stochastic = render_cfg.quadrature.rule == "stochastic"
    per_pixel = render_cfg.pixel_samples ** 2

    def pixel_mean(x):  # [R, ...] -> [R / per_pixel, ...]: each pixel's mean over its consecutive rays
        return x.reshape((-1, per_pixel) + x.shape[1:]).mean(1) if per_pixel > 1 else x

    def local(trainables, scene: PointScene, k_render, rays, background, reduce: bool):
        """Loss terms, their finiteness, gradients and batch statistics of ``rays`` (one device's
        share when ``reduce``: then averaged / summed over the mesh's ``"rays"`` axis)."""
        target = rays.target[:, :3]
        if reduce and stochastic:  # each device jitters its own rays
            k_render = jax.random.fold_in(k_render, jax.lax.axis_index(RAYS))

        def render_part(trainables):  # trainables -> the float inputs of the losses
            pts = scene.points.replace(**trainables["points"])
            out, aux = render_rays_with_aux(render_cfg, trainables["params"], scene.replace(points=pts),
                                            rays, background, k_render if stochastic else None)
            inter = {f.name: getattr(aux, f.name) for f in dataclasses.fields(aux) if f.name != "valid"}
            inter.update(rgb=out.rgb, conf_logit=pts.conf_logit)
            if "ist" in trainables["points"]:
                inter["ist"] = pts.ist
            return inter, (out, aux.valid, pts)

        def loss_part(inter, fixed):  # the float inputs -> the loss terms (cheap; no render)
            out, valid, pts = fixed
            aux = SegmentAux(valid=valid, **{k: v for k, v in inter.items() if k not in ("rgb", "conf_logit", "ist")})
            pts = pts.replace(conf_logit=inter["conf_logit"], **({"ist": inter["ist"]} if "ist" in inter else {}))
            return loss_terms(cfg.loss, out.replace(rgb=pixel_mean(inter["rgb"])), aux, pixel_mean(target), pts)

        inter, render_vjp, fixed = jax.vjp(render_part, trainables, has_aux=True)
        terms, loss_vjp = jax.vjp(lambda x: loss_part(x, fixed), inter)
        # per-term gradients w.r.t. the render's outputs: separate VJPs of the (cheap) loss part, so a
        # NaN in one term never leaks into another's flag through a 0 * NaN
        inter_grads = {k: jax.grad(lambda x, k=k: loss_part(x, fixed)[k])(inter) for k in terms}
        for k in terms:
            stage_check(render_cfg.checks, f"loss/{k}", **{k: terms[k], "grad": inter_grads[k]})
        (inter_cot,) = loss_vjp({k: jnp.asarray(w, terms[k].dtype) for k, w in weights.items()})
        (grads,) = render_vjp(inter_cot)
        stage_check(render_cfg.checks, "backward", grad=grads)
        term_ok = {k: jnp.isfinite(v) & _all_finite(inter_grads[k]) for k, v in terms.items()}
        out = fixed[0]
        mse = (terms["photometric"] if "photometric" in terms
               else jnp.mean(jnp.square(pixel_mean(out.rgb) - pixel_mean(target))))
        stats = {"mse": mse, "opacity": jnp.mean(out.opacity)}
        lost = out.lost
        counts = {f"lost/{k}": jnp.sum(getattr(lost, k)) for k in ("frontier", "slots", "packing", "emitted")}
        counts["lost/rays"] = jnp.asarray(lost.emitted.shape[0], jnp.int32)
        most = {"lost/max_emitted": jnp.max(lost.emitted)}
        if reduce:  # every term is a mean over rays (or over points: equal on every device)
            terms, grads, stats = jax.lax.pmean((terms, grads, stats), RAYS)
            term_ok = jax.tree_util.tree_map(lambda ok: jax.lax.pmin(ok.astype(jnp.int32), RAYS) > 0, term_ok)
            counts, most = jax.lax.psum(counts, RAYS), jax.lax.pmax(most, RAYS)
        return terms, term_ok, grads, {**stats, **counts, **most}

    def step_fn(state: TrainState, scene: PointScene, batch: Batch):
        key, k_render = jax.random.split(state.key)
        trainables = state.trainables
        rays = batch.rays
        if mesh.devices.size == 1 or render_cfg.checks:  # runtime checks run on one device
            terms, term_ok, grads, stats = local(trainables, scene, k_render, rays, batch.background, False)
        else:
            background = jnp.broadcast_to(batch.background, (rays.num_rays, 3))
            terms, term_ok, grads, stats = shard_rays(
                functools.partial(local, reduce=True), mesh, num_replicated=3, out_specs=P())(
                trainables, scene, k_render, rays, background)
        total = sum(jnp.asarray(w, terms[k].dtype) * terms[k] for k, w in weights.items())
        updates, opt_state = optimizer.update(grads, state.opt_state, trainables)
        new_trainables = optax.apply_updates(trainables, updates)
        stage_check(render_cfg.checks, "update", trainables=new_trainables)

        grad_ok = _all_finite(grads)
        update_ok = _all_finite(new_trainables)
        ok = jnp.all(jnp.stack(list(term_ok.values()))) & grad_ok & update_ok

        applied = TrainState(params=new_trainables["params"], points=new_trainables["points"],
                             opt_state=opt_state, step=state.step + 1, key=key, skipped=state.skipped)
        refused = state.replace(skipped=state.skipped + 1)
        new_state = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), applied, refused)

        metrics = {f"loss/{k}": v for k, v in terms.items()}
        metrics["loss/total"] = total
        metrics.update({f"finite/{k}": term_ok[k] for k in terms})
        metrics["finite/grad"] = grad_ok
        metrics["finite/update"] = update_ok
        metrics["ok"] = ok
        metrics["psnr"] = -10.0 * jnp.log10(jnp.maximum(stats["mse"], 1e-10))
        metrics["lr"] = jnp.asarray(schedule(state.step), jnp.float32)
        metrics["grad_norm"] = optax.tree.norm(grads)
        metrics["opacity"] = stats["opacity"]
        metrics.update({k: v for k, v in stats.items() if k.startswith("lost/")})
        return new_state, metrics

    step = checked(step_fn) if render_cfg.checks else jax.jit(step_fn)
    if mesh.devices.size == 1 or render_cfg.checks:
        return step
    replicated = NamedSharding(mesh, P())

    def sharded_step(state: TrainState, scene: PointScene, batch: Batch):
        # the state lives replicated on the mesh from the first step on (a no-op once it does), so
        # the step's input shardings, and with them its compiled program, never change
        return step(jax.device_put(state, replicated), scene, batch)

    return sharded_step


__all__ = ["make_train_step"]
