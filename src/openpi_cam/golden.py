"""Parity check against reference data produced by upstream OpenPI.

`python -m openpi_cam.golden DIR` (or `openpi-cam golden DIR`) reads a folder laid out like
`shared/golden/tiny_pi0_fast` (config.json, checkpoint/params, case_*.npz), runs our model on every case and prints
one line per compared array with its max abs / rel error. Exit status 1 on any mismatch or unreadable input.

The criterion of every non-exact comparison is relative to the compared quantity's scale: it passes when
max |ours - reference| <= r x max |reference| (`compare`; each line prints r, the scale and the bound). Token ids
and decode-step counts are compared exactly. The values of r, with the reasoning behind each, are set once below
(`DEFAULT_TOLERANCES` for pi0-FAST, `FLOW_REL` / `FLOW_GRAD_REL` for pi0 and pi0.5); the command and the tests use
the same ones.
"""

from __future__ import annotations

import dataclasses
import functools
import pathlib
import sys
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from openpi_cam.errors import BadFile, load_json, one_line, reading
from openpi_cam.model import gemma, pi0, pi0_fast_maps, pi0_maps
from openpi_cam.model.observation import Observation
from openpi_cam.model.pi0 import Pi0
from openpi_cam.model.pi0_fast import Pi0FAST, embed_prefix, make_attn_mask, sample_tokens_jit
from openpi_cam.nested import flatten_dict


@dataclasses.dataclass(frozen=True)
class Tolerances:
    """Relative criteria r per kind of compared array: it passes when max |ours - ref| <= r x max |ref|."""

    siglip: float  # per-camera SigLIP outputs
    embeddings: float  # prompt token embeddings (a table lookup times sqrt(width))
    logits: float  # plain-forward, prefix-last and decode-step logits, and the explained logit vectors
    score: float  # Grad-CAM scores (one logit, or a sum of log-probabilities for the chunk)
    gradcam: float  # Grad-CAM maps, channel weights (alpha) and gradient norms

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            if not getattr(self, field.name) > 0:
                raise ValueError(f"tolerance {field.name} must be positive")


# pi0-FAST (tiny_pi0_fast, float32 on both sides), from upstream's own float32 variation recorded beside the goldens
# (README "Verification", verification.json; tests/model/test_model.py recomputes these figures from those files):
# - logits: upstream's evaluations of the same decode logits (jit vs eager, cached decode vs one pass) differ by up
#   to 5.43e-4 at max |logit| 9.51, i.e. UPSTREAM_LOGIT_VARIATION of the scale. SAFETY times that is allowed, since
#   our XLA build orders float32 sums differently again: a systematic 1e-3 error on logits below ~1.7 then fails,
#   while a 4e-4 relative error (a wider configuration's larger logits) passes.
# - scores: a token's score is one of those logits, the chunk's a sum of their log-probabilities: as logits.
# - Grad-CAM maps, channel weights and gradient norms are gradients of those logits. Upstream's two computations of
#   the same maps disagree GRADIENT_AMPLIFICATION times more (relative) than their logits do, so its own variation of
#   the maps is about GRADIENT_AMPLIFICATION x UPSTREAM_LOGIT_VARIATION; 1e-3 (the golden README's suggestion) lies
#   above that and below SAFETY times it, where a looser bound would let real errors through.
# - SigLIP outputs: upstream re-ran them without variation; a relative 1e-6 perturbation of the image tokens moves
#   the logits by up to 1.5e-4 (README probe), so 1e-5 keeps its effect inside the logit criterion.
# - prompt embeddings: a table row times sqrt(width), one float32 rounding; 1e-6 allows any order.
UPSTREAM_LOGIT_VARIATION = 5.7e-5
GRADIENT_AMPLIFICATION = 10
SAFETY = 10
DEFAULT_TOLERANCES = Tolerances(
    siglip=1e-5,
    embeddings=1e-6,
    logits=SAFETY * UPSTREAM_LOGIT_VARIATION,
    score=SAFETY * UPSTREAM_LOGIT_VARIATION,
    gradcam=1e-3,
)


@dataclasses.dataclass
class Comparison:
    case: str
    name: str
    max_abs: float
    scale: float  # max |reference|
    bound: float  # the largest max_abs that passes (0 for exact comparisons)
    ok: bool
    note: str = ""

    @property
    def max_rel(self) -> float:
        return self.max_abs / self.scale if self.scale > 0 else self.max_abs

    def line(self) -> str:
        status = "ok  " if self.ok else "FAIL"
        return (
            f"{status} {self.case:<8} {self.name:<28} max_abs={self.max_abs:.3g} max_rel={self.max_rel:.3g} {self.note}"
        )


def compare(case: str, name: str, got, want, *, rel: float | None = None, exact: bool = False) -> Comparison:
    """`exact`: equal arrays; else max |got - want| <= rel x max |want|."""
    got, want = np.asarray(got), np.asarray(want)
    if got.shape != want.shape:
        note = f"shape {got.shape} != {want.shape}"
        return Comparison(case, name, max_abs=np.inf, scale=np.inf, bound=0.0, ok=False, note=note)
    diff = np.abs(got.astype(np.float64) - want.astype(np.float64))
    max_abs = float(diff.max(initial=0.0))
    scale = float(np.abs(want.astype(np.float64)).max(initial=0.0))
    if exact:
        ok = bool(np.array_equal(got, want))
        return Comparison(case, name, max_abs=max_abs, scale=scale, bound=0.0, ok=ok, note="(exact)")
    if rel is None:
        raise ValueError("give rel= or exact=True")
    bound = rel * scale
    note = f"(<= {rel:g} x max|ref| {scale:.3g} = {bound:.3g})"
    return Comparison(case, name, max_abs=max_abs, scale=scale, bound=bound, ok=max_abs <= bound, note=note)


def load_observation(case: dict, cameras: list[str]) -> Observation:
    return Observation(
        images={c: case[f"image_{c}"] for c in cameras},
        image_masks={c: case[f"image_mask_{c}"] for c in cameras},
        state=case["state"],
        tokenized_prompt=case["tokenized_prompt"],
        tokenized_prompt_mask=case["tokenized_prompt_mask"],
        token_ar_mask=case.get("token_ar_mask"),
        token_loss_mask=case.get("token_loss_mask"),
    )


def plain_prompt_logits(model: Pi0FAST, obs: Observation) -> np.ndarray:
    """One forward over [images | prompt] without cache (make_attn_mask, positions cumsum - 1) -> prompt logits."""
    params, cfg = model.params, model.config
    x, input_mask, ar_mask = embed_prefix(params, model.embed_images(obs), obs, cfg)
    positions = jnp.cumsum(input_mask, axis=-1) - 1
    pre, _ = gemma.forward(params["PaliGemma"]["llm"], x, positions, make_attn_mask(input_mask, ar_mask), cfg.gemma)
    length = obs.tokenized_prompt.shape[1]
    logits = np.asarray(gemma.logits_from_prelogits(params["PaliGemma"]["llm"], pre[:, -length:]))
    return np.where(np.asarray(obs.tokenized_prompt_mask)[..., None], logits, 0.0)


def check_case(
    model: Pi0FAST, name: str, case: dict, cameras: list[str], max_steps: int, tol: Tolerances = DEFAULT_TOLERANCES
) -> list[Comparison]:
    obs = load_observation(case, cameras)
    out: list[Comparison] = []
    image_tokens = np.asarray(model.embed_images(obs))
    for i, cam in enumerate(cameras):
        if f"siglip_{cam}" in case:
            out.append(compare(name, f"siglip_{cam}", image_tokens[:, i], case[f"siglip_{cam}"], rel=tol.siglip))
    if "prompt_token_embeddings" in case:
        emb = gemma.embed_tokens(model.params["PaliGemma"]["llm"], obs.tokenized_prompt, jnp.float32)
        out.append(compare(name, "prompt_token_embeddings", emb, case["prompt_token_embeddings"], rel=tol.embeddings))
    if "prompt_logits" in case:
        out.append(
            compare(name, "prompt_logits", plain_prompt_logits(model, obs), case["prompt_logits"], rel=tol.logits)
        )
    tokens, n_steps, step_logits, _ = sample_tokens_jit(
        model.params,
        obs,
        jax.random.key(0),
        cfg=model.config,
        max_decoding_steps=max_steps,
        temperature=0.0,
        record_logits=True,
    )
    step_logits = np.asarray(step_logits)
    if "output_tokens" in case:
        out.append(compare(name, "output_tokens", tokens, case["output_tokens"], exact=True))
    if "num_decoded_steps" in case:
        out.append(compare(name, "num_decoded_steps", n_steps, case["num_decoded_steps"], exact=True))
    if "prefix_last_logits" in case:
        out.append(compare(name, "prefix_last_logits", step_logits[:, 0], case["prefix_last_logits"], rel=tol.logits))
    if "decode_step_logits" in case:
        n = int(n_steps)
        out.append(
            compare(name, "decode_step_logits", step_logits[:, :n], case["decode_step_logits"][:, :n], rel=tol.logits)
        )
    out += check_gradcam(model, name, case, obs, cameras, tol=tol)
    return out


def _stack(per_camera: dict[str, np.ndarray], cameras: list[str]) -> np.ndarray:
    return np.stack([per_camera[c] for c in cameras], axis=1)  # camera axis after batch


def _gradient_fields(result: pi0_fast_maps.MapResult) -> tuple[tuple[str, dict[str, np.ndarray]], ...]:
    """The golden's names of the Grad-CAM pass's per-camera results."""
    return (("alpha", result.alphas), ("cam", result.by_kind["gradcam"]), ("grad_norm", result.grad_norms))


def check_gradcam(
    model: Pi0FAST, name: str, case: dict, obs: Observation, cameras: list[str], tol: Tolerances = DEFAULT_TOLERANCES
) -> list[Comparison]:
    """The `gc_replay_*` references: Grad-CAM of the logits upstream's cached decoding used."""
    out: list[Comparison] = []
    generated = np.asarray(case["output_tokens"]).astype(np.int32)
    steps = sorted(int(k.split("_")[2][1:]) for k in case if k.startswith("gc_replay_k") and k.endswith("_score"))
    for k in steps:
        prefix = f"gc_replay_k{k}"
        res = pi0_fast_maps.gradcam_for_action_token(model, obs, generated, k)
        out.append(compare(name, f"{prefix}_logits", res.logits, case[f"{prefix}_logits"], rel=tol.logits))
        out.append(compare(name, f"{prefix}_score", res.score, case[f"{prefix}_score"], rel=tol.score))
        for key, ours in _gradient_fields(res):
            want = case[f"{prefix}_{key}"]
            out.append(compare(name, f"{prefix}_{key}", _stack(ours, cameras), want, rel=tol.gradcam))
    if "gc_replay_chunk_score" in case:
        n = int(case.get("num_decoded_steps", generated.shape[1]))
        res = pi0_fast_maps.maps_for_chunk(model, obs, generated, list(range(n)))
        out.append(compare(name, "gc_replay_chunk_score", res.score, case["gc_replay_chunk_score"], rel=tol.score))
        for key, ours in _gradient_fields(res):
            want = case[f"gc_replay_chunk_{key}"]
            out.append(compare(name, f"gc_replay_chunk_{key}", _stack(ours, cameras), want, rel=tol.gradcam))
    return out


# pi0 / pi0.5 (tiny_pi0, tiny_pi05, and the policies built on them): upstream's own spread (jit vs eager) is about
# 2e-6 on x_0, but it shares one operation order; the float32 evaluation error of these functions is larger: the
# float32 velocity differs from the float64 one by 2.2e-4 at |v| <= 6.6 (pi0.5 case_a), 3.4e-5 of the largest value.
# FLOW_REL (1.5x that, rounded up) for values (SigLIP tokens, every Euler iterate and velocity, actions, the loss,
# scores); FLOW_GRAD_REL (the goldens' suggestion) for gradients and their reductions, whose float32 error reaches
# 6.2e-5 of their largest magnitude (pi0.5 case_a chunk). Time steps compare exactly.
FLOW_REL = 5e-5
FLOW_GRAD_REL = 1e-4
FLOW_TARGETS = {"gc_h0_d0": (0, 0), "gc_h0_d6": (0, 6), "gc_h9_d3": (9, 3), "gc_chunk": pi0_maps.CHUNK}


# LeRobot's goldens (lerobot_pi0_tiny, lerobot_pi05_tiny: LeRobot 0.6.1's PyTorch port, float32 on CPU), served with
# LeRobot's time grid (`Pi0Config.flow_time`). Each golden states its own float32 variation: a row of its batch of two
# against the same frame run alone (`meta/batch2_row_vs_single_maxdiff`), relative to max |chunk| (`lerobot_variation`).
# Chunks, normalised and post-processed, and the explained objective may differ SAFETY times that, since our XLA build
# orders the float32 sums differently again; the gradient GRADIENT_AMPLIFICATION times more, as pi0-FAST's gradients
# vary that much more than their logits. Model-space images are one bilinear blend of four float32 values that torch
# rounds in another order: LEROBOT_IMAGE_REL (4 float32 epsilons) of their range. Tokens, masks, the prompt text and
# the normalised state (elementwise float32 arithmetic in LeRobot's order) compare exactly.
LEROBOT_IMAGE_REL = 4 * float(np.finfo(np.float32).eps)


def lerobot_variation(row_vs_single_maxdiff: np.ndarray, batch_chunk: np.ndarray) -> float:
    """A LeRobot golden's own float32 variation relative to its chunk's scale."""
    return float(np.max(row_vs_single_maxdiff)) / float(np.abs(batch_chunk).max())


def flow_image_gradient(
    model: Pi0, obs: Observation, noise: np.ndarray, weights: np.ndarray, camera: str
) -> tuple[float, np.ndarray]:
    """(sum(weights * x_0[..., :A]), its gradient w.r.t. `camera`'s model-space image [B, H, W, 3]) through all the
    Euler steps from `noise`, the other inputs fixed; A is the weights' last dim."""

    def objective(image: jax.Array) -> jax.Array:
        moved = dataclasses.replace(obs, images={**obs.images, camera: image})
        x_0 = pi0.sample_actions(model.params, moved, jnp.asarray(noise, jnp.float32), cfg=model.config)
        return jnp.sum(jnp.asarray(weights) * x_0[..., : weights.shape[-1]])

    value, grad = jax.jit(jax.value_and_grad(objective))(jnp.asarray(obs.images[camera]))
    return float(value), np.asarray(grad)


# One compiled program per model config for every case (a fresh `jax.jit` per case would retrace each time).
_denoise_recorded = jax.jit(functools.partial(pi0.denoise, record=True), static_argnames="cfg")


def check_flow_case(model: Pi0, name: str, d: dict, cameras: list[str]) -> list[Comparison]:
    """One pi0 / pi0.5 golden case: SigLIP tokens, every Euler iterate and velocity, the actions, the training loss
    for the case's explicit noise and time, and the gradient targets' scores, channel weights, maps and norms."""
    obs = Observation(
        images={c: d[f"image_{c}"] for c in cameras},
        image_masks={c: d[f"image_mask_{c}"] for c in cameras},
        state=d["state"],
        tokenized_prompt=d["tokenized_prompt"],
        tokenized_prompt_mask=d["tokenized_prompt_mask"],
    )
    out = []
    E = np.asarray(model.embed_images(obs))
    out += [compare(name, f"siglip_{c}", E[:, i], d[f"siglip_{c}"], rel=FLOW_REL) for i, c in enumerate(cameras)]
    steps = d["v_t_steps"].shape[1]  # x_t_steps also holds x_0 after the last step
    prepared = pi0.preprocess(obs, model.config)
    x_0, (xs, vs, _) = _denoise_recorded(model.params, jnp.asarray(E), prepared, jnp.asarray(d["noise"]), model.config)
    out.append(compare(name, "x_t_steps", xs, d["x_t_steps"][:, :steps], rel=FLOW_REL))
    out.append(compare(name, "v_t_steps", vs, d["v_t_steps"], rel=FLOW_REL))
    out.append(compare(name, "actions", x_0, d["actions"], rel=FLOW_REL))
    loss = model.compute_loss(obs, d["loss_actions"], d["loss_noise"], d["loss_time"])
    out.append(compare(name, "loss", loss, d["loss"], rel=FLOW_REL))
    res = pi0_maps.maps_for_actions(model, obs, d["noise"], list(FLOW_TARGETS.values()))
    for t, key in enumerate(FLOW_TARGETS):
        out.append(compare(name, f"{key}_score", res.score[:, t], d[f"{key}_score"], rel=FLOW_REL))
        for field, ours in (("alpha", res.alphas), ("grad_norm", res.grad_norms), ("cam", res.by_kind["gradcam"])):
            got = np.stack([ours[c][:, t] for c in cameras], axis=1)
            want = d[f"{key}_{field}"]
            out.append(compare(name, f"{key}_{field}", got.reshape(want.shape), want, rel=FLOW_GRAD_REL))
    return out


def run_golden(
    folder: str | pathlib.Path,
    *,
    verbose: bool = True,
    scan: bool | None = None,
    tolerances: Tolerances = DEFAULT_TOLERANCES,
) -> list[Comparison]:
    """Every comparison of a golden folder; `scan` forces the layer-stack layout (None: the read-back default)."""
    folder = pathlib.Path(folder)
    if not (folder / "config.json").is_file() and list(folder.glob("*_param_tree.json")):
        return _run_param_trees(folder, verbose)
    config = load_json(folder / "config.json")
    if "pi0_config" in config:
        return _run_flow_golden(folder, config, verbose)
    data_cfg = config.get("pi0_fast_config", {})
    model = Pi0FAST.from_checkpoint(
        folder / "checkpoint" / "params",
        dtype=data_cfg.get("dtype", "float32"),
        scan=scan,
        action_dim=data_cfg.get("action_dim", 32),
        action_horizon=data_cfg.get("action_horizon", 32),
        max_token_len=data_cfg.get("max_token_len", 250),
    )
    cameras = list(config["camera_keys"])
    max_steps = int(config.get("max_decoding_steps", 256))
    results: list[Comparison] = []
    for name, case in read_cases(folder):
        for comp in check_case(model, name, case, cameras, max_steps=max_steps, tol=tolerances):
            results.append(comp)
            if verbose:
                print(comp.line(), flush=True)
    return results


def read_cases(folder: pathlib.Path) -> list[tuple[str, dict]]:
    case_files = sorted(folder.glob("case_*.npz"))
    if not case_files:
        raise FileNotFoundError(f"no case_*.npz files in {folder}")
    cases = []
    for path in case_files:
        cases.append((path.stem, read_npz(path)))
    return cases


def read_npz(path: pathlib.Path) -> dict[str, np.ndarray]:
    """Every array of a golden's `.npz` file."""
    with reading(path, "npz file"), np.load(path, allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}


def _run_flow_golden(folder: pathlib.Path, config: dict, verbose: bool) -> list[Comparison]:
    data_cfg = config["pi0_config"]
    model = Pi0.from_checkpoint(
        folder / "checkpoint" / "params",
        dtype="float32",
        action_horizon=data_cfg["action_horizon"],
        max_token_len=data_cfg["max_token_len"],
    )
    results = []
    for name, case in read_cases(folder):
        results += report(check_flow_case(model, name, case, list(config["camera_keys"])), verbose)
    return results


def report(results: list[Comparison], verbose: bool) -> list[Comparison]:
    if verbose:
        for comp in results:
            print(comp.line(), flush=True)
    return results


def _run_param_trees(folder: pathlib.Path, verbose: bool) -> list[Comparison]:
    """Full-size parameter trees (`param_trees/`): the tree our initialiser builds for the architecture the shapes
    describe (`jax.eval_shape`, no weights) has exactly upstream's paths and shapes."""
    results = []
    for path in sorted(folder.glob("*_param_tree.json")):
        upstream = {k: tuple(v["shape"]) for k, v in load_json(path)["leaves"].items()}
        gemma_cfg, expert, siglip, pi05 = pi0.pi0_architecture_from_params(upstream)
        cfg = pi0.Pi0Config(gemma_cfg, expert, siglip, pi05)
        ours = flatten_dict(jax.eval_shape(functools.partial(pi0.init_params, cfg), jax.random.key(0)))
        ours = {k: tuple(v.shape) for k, v in ours.items()}
        differing = sorted(k for k in set(ours) | set(upstream) if ours.get(k) != upstream.get(k))
        note = f"{len(upstream)} leaves" + (f"; first difference {differing[0]}" if differing else "")
        results.append(
            Comparison(
                path.stem,
                "tree",
                max_abs=float(len(differing)),
                scale=float(len(upstream)),
                bound=0.0,
                ok=not differing,
                note=note,
            )
        )
    return report(results, verbose)


def check_folder(folder: pathlib.Path, run: Callable[[pathlib.Path], list[Comparison]] | None = None) -> int:
    """Prints every comparison of a golden folder (`run`, default `run_golden`) and a verdict line; the exit status
    (1 on any mismatch or unreadable input)."""
    try:
        results = (run or run_golden)(folder)
    except BadFile as e:  # its message names the file and what is wrong
        print(f"FAIL cannot check {folder}: {e}")
        return 1
    except Exception as e:  # unreadable input is a failure of the check, reported in one line
        print(f"FAIL cannot check {folder}: {type(e).__name__}: {one_line(e)}")
        return 1
    failed = [r for r in results if not r.ok]
    print(f"{len(results) - len(failed)} passed, {len(failed)} failed")
    return 1 if failed else 0


if __name__ == "__main__":
    if len(sys.argv) != 2:
        print("usage: python -m openpi_cam.golden DIR", file=sys.stderr)
        raise SystemExit(2)
    raise SystemExit(check_folder(pathlib.Path(sys.argv[1])))
