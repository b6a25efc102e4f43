"""Would a gradient-weighted attention relevancy (Chefer et al. 2021) be a more faithful map than those we ship?

Issue 15 asks for it "if it measures better". This script measures it on a pi0-FAST run directory that holds the
`gradnorm`, `ig` and `occlusion` maps with model frames (the bundled demo writes one), on the very steps and with the
very painting `openpi-cam faithfulness` uses:

* relevancy, for the explained score s (the run's target) of every step: R = I over the replayed sequence (prefix and
  fed tokens, upstream's decoding quirks included), then for each Gemma layer from the bottom
  R <- R + mean_heads(relu(ds/dA * A)) @ R, A the layer's attention probabilities; the map of a camera is the sum,
  over the outputs the score reads, of R's row restricted to that camera's image tokens;
* per kind (relevancy, gradnorm, ig, occlusion): deletion at k = 1, 2, 4 (paint the map's top-k patches with the
  run's baseline frame, re-run, divide the drop by the step's single-patch occlusion optimum: the stored occlusion
  map's maximum), top-1 agreement with occlusion, pointing at the target block, and model randomisation
  (|Spearman| with the same kind from a model whose language model is re-initialised, next to the null between
  unrelated steps; relevancy only, the others are in the run's faithfulness report).

The relevancy is computed by its own one-pass replay (the attention probabilities need a probe that the served
model does not carry); the run stops unless that replay reproduces every logged score.

    openpi-cam demo --out DIR --num-episodes 100 --max-calls 1 --seed 1000 --no-render --no-faithfulness
    python benchmarks/relevancy_faithfulness.py DIR/<run> [--max-steps N]
"""

from __future__ import annotations

import argparse
import functools
import platform
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from openpi_cam.cam import faithfulness as fm
from openpi_cam.cam.faithfulness_run import painting_options, step_model_inputs
from openpi_cam.cam.run_format import load_run
from openpi_cam.cli.faithfulness import load_policy
from openpi_cam.model import gemma
from openpi_cam.model.observation import preprocess_observation
from openpi_cam.model.paligemma import embed_images, embed_prefix, make_attn_mask
from openpi_cam.model.pi0_fast import decode_positions, decode_window, left_to_right_align
from openpi_cam.vocabulary import ExplainOptions

KS = (1, 2, 4)
SHIPPED = ("gradnorm", "ig", "occlusion")
# float32 rounding of two orderings of the same sums: 3.7e-6 at most on the demo's 100 scenes.
REPLAY_TOLERANCE = 1e-4


def _layer(h, p, positions, mask, probe, cfg):
    """One Gemma layer over the whole sequence h [B, T, D] with attention probabilities A + probe; -> (h, A)."""
    x = gemma.rms_norm(h, p["pre_attention_norm"]["scale"])
    q = jnp.einsum("BTD,NDH->BTNH", x, p["attn"]["q_einsum"]["w"].astype(x.dtype))
    k, v = jnp.einsum("BSD,CKDH->CBSKH", x, p["attn"]["kv_einsum"]["w"].astype(x.dtype))
    q = gemma.apply_rope(q, positions) * cfg.head_dim**-0.5
    k = gemma.apply_rope(k, positions)
    slots = mask.shape[-1]
    pad = ((0, 0), (0, slots - h.shape[1]), (0, 0), (0, 0))  # cache slots no token has written stay zero
    k, v = jnp.pad(k.astype(x.dtype), pad), jnp.pad(v, pad)
    b, t, n, hd = q.shape
    q = q.reshape(b, t, cfg.num_kv_heads, n // cfg.num_kv_heads, hd)
    logits = jnp.einsum("BTKGH,BSKH->BKGTS", q, k, preferred_element_type=jnp.float32)
    probs = jax.nn.softmax(jnp.where(mask[:, None, None], logits, gemma.BIG_NEG), axis=-1)
    encoded = jnp.einsum("BKGTS,BSKH->BTKGH", (probs + probe).astype(x.dtype), v).reshape(b, t, n, hd)
    h = h + jnp.einsum("BTNH,NHD->BTD", encoded, p["attn"]["attn_vec_einsum"]["w"].astype(x.dtype))
    h = h + gemma.feed_forward(gemma.rms_norm(h, p["pre_ffw_norm"]["scale"]), p["mlp"])
    return h, probs


def _sequence(params, obs, fed, cfg):
    """Prefix (right-aligned, as upstream's prefill) followed by fed[:, :-1] in one sequence, with the masks and RoPE
    positions of upstream's prefill and decode steps. -> (x [B, T, D], positions [B, T], mask [B, T, P + S], P,
    the roll that right-aligned the prefix [B])"""
    llm = params["PaliGemma"]["llm"]
    x, input_mask, ar_mask = embed_prefix(params, embed_images(params, obs, cfg), obs, cfg)
    seqlen = jnp.max(input_mask * jnp.arange(input_mask.shape[1]), axis=1) + 1
    x, input_mask, attn = left_to_right_align(x, input_mask, make_attn_mask(input_mask, ar_mask))
    p, s = x.shape[1], fed.shape[1]
    prefill_len = jnp.sum(input_mask, axis=-1)
    step = jnp.arange(s - 1)
    mask = jnp.concatenate(
        [jnp.pad(attn, ((0, 0), (0, 0), (0, s))), decode_window(p - prefill_len, p, s, step)], axis=1
    )
    positions = jnp.concatenate([jnp.cumsum(input_mask, axis=-1) - 1, decode_positions(prefill_len, step)], axis=1)
    emb = gemma.embed_tokens(llm, fed[:, :-1], jnp.dtype(cfg.dtype))
    return jnp.concatenate([x, emb], axis=1), positions, mask, p, seqlen


@functools.partial(jax.jit, static_argnames=("cfg",))
def _relevancy(params, obs, fed, out_rows, targets, *, cfg):
    """(score [B], relevancy of each prefix token to the explained outputs [B, P], cameras first). The score is
    sum_k log p(targets[:, k]) at outputs out_rows[:, k] of the one-pass replay."""
    x, positions, mask, p, seqlen = _sequence(params, obs, fed, cfg)
    llm = params["PaliGemma"]["llm"]
    b, t = x.shape[:2]
    heads = (cfg.gemma.num_kv_heads, cfg.gemma.num_heads // cfg.gemma.num_kv_heads)
    probes = [jnp.zeros((b, *heads, t, mask.shape[-1]), jnp.float32)] * cfg.gemma.depth

    def score_fn(probes):
        h, probs = x, []
        for i, probe in enumerate(probes):
            h, a = _layer(h, jax.tree.map(lambda w: w[i], llm["layers"]), positions, mask, probe, cfg.gemma)  # noqa: B023
            probs.append(a)
        pre = jnp.take_along_axis(gemma.rms_norm(h, llm["final_norm"]["scale"]), out_rows[..., None], axis=1)
        logp = jax.nn.log_softmax(gemma.logits_from_prelogits(llm, pre).astype(jnp.float32), -1)
        return jnp.sum(jnp.take_along_axis(logp, targets[..., None], -1)), probs

    (score, probs), grads = jax.value_and_grad(score_fn, has_aux=True)(probes)
    # The explained rows of R = (I + A_L) ... (I + A_1), A_l = mean over heads of relu(ds/dA * A), as a row vector
    # taken down the stack: O(T^2) per layer instead of R's O(T^3).
    r = jnp.zeros((b, t)).at[jnp.arange(b)[:, None], out_rows].add(1.0)
    for a, g in zip(probs[::-1], grads[::-1], strict=True):
        r = r + jnp.einsum("BT,BTS->BS", r, jnp.mean(jax.nn.relu(a * g)[..., :t], axis=(1, 2)))
    unaligned = jax.vmap(jnp.roll)(r[:, :p], seqlen)  # undo the right-alignment: cameras first, as embed_prefix
    return score, unaligned


def relevancy_maps(model, obs, fed, steps) -> tuple[float, dict[str, np.ndarray]]:
    """(score, camera -> relevancy map [Hp, Wp]) of one step (B = 1) whose score sums log p(fed[k]) over steps."""
    cfg = model.config
    obs = preprocess_observation(obs, cfg.image_resolution)
    n, grid = cfg.siglip.num_tokens, cfg.siglip.grid
    p = len(obs.images) * n + obs.tokenized_prompt.shape[1]
    steps = np.asarray(steps)
    out_rows = np.where(steps == 0, p - 1, p + steps - 1)[None]  # the output that predicts each explained step
    fed = np.asarray(fed, np.int32)
    score, rel = _relevancy(model.params, obs, jnp.asarray(fed), out_rows, fed[:, steps], cfg=cfg)
    prefix = np.asarray(rel)[0]
    return float(score[()]), {c: prefix[i * n : (i + 1) * n].reshape(grid) for i, c in enumerate(obs.images)}


def _median(values):
    return f"{statistics.median(values):.2f}" if values else "-"


def _mean_ci(values):
    if not values:
        return "-"
    mean, low, high = fm.bootstrap_mean_ci(values)
    return f"{mean:.2f} [{low:.2f}, {high:.2f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--max-steps", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0, help="seed of the LLM re-initialisation")
    args = parser.parse_args()

    run = load_run(args.run_dir)
    policy = load_policy(
        run.run_info.get("config") or {},
        config=None,
        checkpoint_dir=None,
        paligemma_tokenizer=None,
        fast_tokenizer=None,
        dtype=None,
    )
    explainer = policy.explainer
    random_model = explainer.randomized("llm", args.seed).model
    steps = [s for s in run.steps if set(SHIPPED) <= set(s.map_kinds)][: args.max_steps]
    kinds = ("relevancy", *SHIPPED)
    cams = list(steps[0].meta["cameras"])
    deletion = {(c, k, kk): [] for c in cams for k in kinds for kk in KS}
    top1 = {(c, k): [] for c in cams for k in kinds}
    pointing = {(c, k): [] for c in cams for k in kinds}
    chance: list[float] = []
    rel_maps: dict[str, list[np.ndarray]] = {c: [] for c in cams}
    rand_rho: dict[str, list[float]] = {c: [] for c in cams}
    score_errors = []
    times: dict[str, list[float]] = {"relevancy": [], "gradcam + gradnorm": []}
    for index, step in enumerate(steps):
        obs, outputs, sample_inputs = step_model_inputs(step)
        decode_steps = np.asarray(step.meta["decode_steps"], np.int32)
        # Timed side by side, interleaved step by step; the first step compiles both and is not counted.
        t0 = time.perf_counter()
        score, rel = relevancy_maps(explainer.model, obs, outputs, decode_steps)
        t1 = time.perf_counter()
        explainer.explain(obs, outputs, ExplainOptions(step.meta["target"], maps=("gradcam", "gradnorm")))
        t2 = time.perf_counter()
        if index:
            times["relevancy"].append(t1 - t0)
            times["gradcam + gradnorm"].append(t2 - t1)
        score_errors.append(abs(score - float(step.meta["score"])) / max(1.0, abs(score)))
        _, rel_random = relevancy_maps(random_model, obs, outputs, decode_steps)
        grid = rel[cams[0]].shape
        maps = {c: {"relevancy": rel[c], **{k: fm.reduce_map(step.maps_of(k)[c]) for k in SHIPPED}} for c in cams}
        masks = {
            c: np.concatenate(
                [np.zeros((1, *grid), bool)]
                + [fm.top_k_masks(fm.patch_order(maps[c][k]), grid)[list(KS)] for k in kinds]
            )
            for c in cams
        }
        scores = explainer.rescore(obs, outputs, sample_inputs, step.meta, masks, painting_options(step, "run"))
        for c in cams:
            occlusion = maps[c]["occlusion"]
            optimum = float(occlusion.max())
            drops = (scores[c][0] - scores[c][1:]).reshape(len(kinds), len(KS))
            cells = fm.target_cells(step.meta, c, grid, step.model_frames[c].shape[:2], step.extra)
            for i, k in enumerate(kinds):
                if optimum > 0:
                    for j, kk in enumerate(KS):
                        deletion[c, k, kk].append(drops[i, j] / optimum)
                    top1[c, k].append(fm.top1_agreement(maps[c][k], occlusion))
                if cells is not None:
                    pointing[c, k].append(fm.pointing_hit(maps[c][k], cells))
            if cells is not None and c == cams[0]:
                chance.append(fm.pointing_chance(cells))
            rel_maps[c].append(rel[c])
            rand_rho[c].append(abs(fm.spearman(rel[c], rel_random[c])))

    print(f"{args.run_dir}: {len(steps)} steps, target {steps[0].meta['target']}, {platform.machine()} CPU")
    print(f"one-pass replay vs logged score: max relative error {max(score_errors):.1e}")
    if max(score_errors) > REPLAY_TOLERANCE:
        raise SystemExit("the one-pass replay does not reproduce the logged scores: its maps would explain another")
    ratio = statistics.median(a / b for a, b in zip(times["relevancy"], times["gradcam + gradnorm"], strict=True))
    print(
        "median ms: "
        + ", ".join(f"{k} {1e3 * statistics.median(v):.1f}" for k, v in times.items())
        + f"; relevancy / gradient pass, per step: {ratio:.2f}x (side by side, step by step)"
    )
    for c in cams:
        null = fm.null_abs_spearman(rel_maps[c])
        print(f"\n{c}: pointing chance {statistics.mean(chance):.2f}" if chance and c == cams[0] else f"\n{c}:")
        print("| kind | deletion k=1 median | mean [95% CI] | k=2 | k=4 | top-1 = occlusion | pointing |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
        for k in kinds:
            agree = f"{100 * np.mean(top1[c, k]):.0f}%" if top1[c, k] else "-"
            point = f"{100 * np.mean(pointing[c, k]):.0f}%" if pointing[c, k] else "-"
            cols = " | ".join(_median(deletion[c, k, kk]) for kk in KS)
            cols = cols.replace(" | ", f" | {_mean_ci(deletion[c, k, 1])} | ", 1)
            print(f"| {k} | {cols} | {agree} | {point} |")
        print(
            f"relevancy randomisation (LLM re-initialised): |rho| {np.mean(rand_rho[c]):.2f} (null {np.mean(null):.2f})"
        )


if __name__ == "__main__":
    main()
