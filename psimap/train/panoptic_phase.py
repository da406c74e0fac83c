"""Joint panoptic phase of training (paper §4.2): after the geometry schedule has frozen the surfel
set, the panoptic field is trained with lambda_3 L_ins + lambda_4 L_sem added to the geometry
losses, and its gradients also reach the geometry through the Top-K blending weights.

Running it on the frozen surfel set means densification never has to remap the per-surfel
features, and the queries are initialised from masks back-projected onto settled geometry.
"""
from __future__ import annotations

import time

import numpy as np
import torch

from psimap import PsimapError


def has_labels(frames) -> bool:
    return any(fr.instance is not None or fr.semantic is not None for fr in frames)


def panoptic_phase(params: dict, frames, classes, cfg, *, index, spacing: float, extent: float,
                   lr_means: float, generator: torch.Generator, rng: np.random.Generator, log,
                   progress: bool) -> tuple[dict, dict]:
    """Train the panoptic field jointly with geometry; returns (checkpoint part, metrics).

    params: the trainer's leaf tensors (means, quats, log_scales, opacity_logit, color_logit);
    frames: TrainFrames with `semantic` / `instance` label maps. The checkpoint part has
    "surfels" (semantic, instance, instance_id, semantic_id) and "queries".
    """
    from tqdm import tqdm

    from psimap.panoptic.field import PanopticField, init_queries, visible_surfels
    from psimap.render import rasterize
    from psimap.train import losses as L
    from psimap.train.trainer import PARAM_NAMES, _optimizer, loss_terms

    t0 = time.perf_counter()
    pcfg = cfg.panoptic_config()
    labelled = [fr for fr in frames if fr.instance is not None or fr.semantic is not None]
    queries = init_queries(labelled, classes, pcfg, scene_scale=extent, generator=generator)
    n = int(params["means"].shape[0])
    field = PanopticField(n, classes, queries, pcfg, generator=generator)
    q0 = queries.count
    log(f"panoptic: {q0} initial queries from {min(pcfg.init_frames, len(labelled))} frames, "
        f"{len(classes)} classes")
    for k in PARAM_NAMES:
        params[k] = params[k].detach().clone().requires_grad_(cfg.panoptic_geometry)
    optimizer = None
    if cfg.panoptic_geometry:
        optimizer, _ = _optimizer(params, cfg, extent)
        optimizer.param_groups[0]["lr"] = lr_means          # continue at the decayed position step
    order = rng.integers(0, len(labelled), size=cfg.panoptic_iters)
    bar = tqdm(total=cfg.panoptic_iters, desc="panoptic", disable=not progress, dynamic_ncols=True)
    guard, removed_total = L.NonFiniteGuard(), 0
    for step in range(cfg.panoptic_iters):
        fr = labelled[int(order[step])]
        q = params["quats"]
        quats = q / q.norm(dim=1, keepdim=True).clamp_min(1e-12)
        scales = params["log_scales"].exp()
        opac = torch.sigmoid(params["opacity_logit"])
        colors = torch.sigmoid(params["color_logit"])
        vis = visible_surfels(params["means"].detach(), quats.detach(), scales.detach(), opac.detach(),
                              fr.viewmat, fr.K, fr.width, fr.height)

        def render(idx, feats, topk, fr=fr, quats=quats, scales=scales, opac=opac, colors=colors):
            return rasterize(params["means"][idx], quats[idx], scales[idx], opac[idx], colors[idx],
                             fr.viewmat, fr.K, fr.width, fr.height, features=feats, topk=topk,
                             backend="auto")

        field.zero_grad()
        terms = {}
        if optimizer is not None:
            terms, _ = loss_terms(params, fr, cfg, index, spacing, True, generator)
        l_ins, l_sem, info = field.losses(render, params["means"], vis, fr.instance, fr.semantic,
                                          fr.K, fr.viewmat, fr.width, fr.height, generator=generator,
                                          depth=fr.depth)
        terms["ins"], terms["sem"] = l_ins, l_sem
        bad = L.first_nonfinite(terms)
        if bad is None:
            sum(terms.values()).backward()
            grads = [p.grad for p in (*(params[k] for k in PARAM_NAMES), field.semantic, field.instance)
                     if p.grad is not None]
            if not all(bool(torch.isfinite(g).all()) for g in grads):
                bad = "gradient"
        if bad is not None:
            field.zero_grad()
            if optimizer is not None:
                optimizer.zero_grad(set_to_none=True)
            try:
                guard.skip(f"'{bad}'", f"panoptic training diverged at step {step} (frame {fr.name})")
            except PsimapError:
                bar.close()
                raise
            continue
        guard.ok()
        field.step()
        if optimizer is not None:
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        removed = field.maybe_adjust(params["means"].detach())
        removed_total += removed
        if removed:
            drops = ", ".join(f"{v} {k}" for k, v in field.last_drops.items() if v)
            log(f"panoptic step {step}: dropped {removed} queries ({drops}), {field.queries.count} left")
        if (step + 1) % cfg.log_every == 0:
            bar.set_postfix(ins=f"{float(l_ins.detach()):.3f}", sem=f"{float(l_sem.detach()):.3f}",
                            queries=field.queries.count)
        bar.update(1)
    bar.close()
    for k in PARAM_NAMES:
        params[k] = params[k].detach()
    state = field.state_for_checkpoint(params["means"])
    n_inst = int(state["surfels"]["instance_id"].max()) if n else 0
    # the checkpoint keeps only the queries that own an instance at export
    q_final = int(state["queries"]["feature"].shape[0])
    metrics = {"panoptic_steps": int(cfg.panoptic_iters), "panoptic_seconds": time.perf_counter() - t0,
               "queries_initial": int(q0), "queries_final": q_final,
               "queries_removed": int(removed_total), "instances": n_inst,
               "panoptic_skipped_steps": int(guard.skipped)}
    log(f"panoptic: {q_final} queries (from {q0}), {n_inst} instances, "
        f"{metrics['panoptic_seconds']:.1f} s")
    return state, metrics
