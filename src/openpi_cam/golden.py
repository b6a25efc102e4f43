"""Parity check against reference data produced by upstream OpenPI.

`python -m openpi_cam.golden DIR` (or `openpi-cam golden DIR`) reads a folder laid out like
`shared/golden/tiny_pi0_fast` (config.json, checkpoint/params, case_*.npz), runs our model on every case and prints
one line per compared array with its max abs / rel error. Exit status 1 on any mismatch or unreadable input.

Tolerances (float32; from the golden's own measurements of upstream-vs-upstream agreement, README "Verification"):
SigLIP outputs and prompt embeddings atol 1e-4; logits atol 2e-3 (upstream's own evaluations differ by up to 5.4e-4
over 16 steps); tokens exact; Grad-CAM maps / alphas / grad norms within 1e-3 of their max; scores atol 2e-3.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np

from openpi_cam.model import gemma, pi0_fast_maps
from openpi_cam.model.observation import Observation
from openpi_cam.model.pi0_fast import Pi0FAST, embed_prefix, make_attn_mask, sample_tokens_jit

ATOL = {"siglip": 1e-4, "embeddings": 1e-4, "logits": 2e-3, "score": 2e-3}
REL_TO_MAX = 1e-3


@dataclasses.dataclass
class Comparison:
    case: str
    name: str
    max_abs: float
    max_rel: float
    ok: bool
    note: str = ""

    def line(self) -> str:
        status = "ok  " if self.ok else "FAIL"
        return (
            f"{status} {self.case:<8} {self.name:<28} max_abs={self.max_abs:.3g} max_rel={self.max_rel:.3g} {self.note}"
        )


def compare(
    case: str, name: str, got, want, *, atol: float | None = None, rel_to_max: float | None = None, exact: bool = False
) -> Comparison:
    got, want = np.asarray(got), np.asarray(want)
    if got.shape != want.shape:
        return Comparison(case, name, np.inf, np.inf, False, f"shape {got.shape} != {want.shape}")
    diff = np.abs(got.astype(np.float64) - want.astype(np.float64))
    max_abs = float(diff.max(initial=0.0))
    scale = float(np.abs(want).max(initial=0.0))
    max_rel = max_abs / scale if scale > 0 else max_abs
    if exact:
        return Comparison(case, name, max_abs, max_rel, bool(np.array_equal(got, want)), "(exact)")
    if rel_to_max is not None:
        return Comparison(case, name, max_abs, max_rel, max_rel <= rel_to_max, f"(<= {rel_to_max:g} of max)")
    return Comparison(case, name, max_abs, max_rel, max_abs <= atol, f"(atol {atol:g})")


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


def check_case(model: Pi0FAST, name: str, case: dict, cameras: list[str], max_steps: int) -> list[Comparison]:
    obs = load_observation(case, cameras)
    out: list[Comparison] = []
    image_tokens = np.asarray(model.embed_images(obs))
    for i, cam in enumerate(cameras):
        if f"siglip_{cam}" in case:
            out.append(compare(name, f"siglip_{cam}", image_tokens[:, i], case[f"siglip_{cam}"], atol=ATOL["siglip"]))
    if "prompt_token_embeddings" in case:
        emb = gemma.embed_tokens(model.params["PaliGemma"]["llm"], obs.tokenized_prompt, jnp.float32)
        out.append(
            compare(name, "prompt_token_embeddings", emb, case["prompt_token_embeddings"], atol=ATOL["embeddings"])
        )
    if "prompt_logits" in case:
        out.append(
            compare(name, "prompt_logits", plain_prompt_logits(model, obs), case["prompt_logits"], atol=ATOL["logits"])
        )
    tokens, n_steps, step_logits = sample_tokens_jit(
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
        out.append(
            compare(name, "prefix_last_logits", step_logits[:, 0], case["prefix_last_logits"], atol=ATOL["logits"])
        )
    if "decode_step_logits" in case:
        n = int(n_steps)
        out.append(
            compare(
                name, "decode_step_logits", step_logits[:, :n], case["decode_step_logits"][:, :n], atol=ATOL["logits"]
            )
        )
    out += check_gradcam(model, name, case, obs, cameras)
    return out


def _stack(result, field: str, cameras: list[str]) -> np.ndarray:
    return np.stack([getattr(result, field)[c] for c in cameras], axis=1)  # camera axis after batch


def check_gradcam(model: Pi0FAST, name: str, case: dict, obs: Observation, cameras: list[str]) -> list[Comparison]:
    """The `gc_replay_*` references: Grad-CAM of the logits upstream's cached decoding used."""
    out: list[Comparison] = []
    generated = np.asarray(case["output_tokens"]).astype(np.int32)
    steps = sorted(int(k.split("_")[2][1:]) for k in case if k.startswith("gc_replay_k") and k.endswith("_score"))
    for k in steps:
        prefix = f"gc_replay_k{k}"
        res = pi0_fast_maps.gradcam_for_action_token(model, obs, generated, k)
        out.append(compare(name, f"{prefix}_logits", res.logits, case[f"{prefix}_logits"], atol=ATOL["logits"]))
        out.append(compare(name, f"{prefix}_score", res.score, case[f"{prefix}_score"], atol=ATOL["score"]))
        for field, key in (("alphas", "alpha"), ("maps", "cam"), ("grad_norms", "grad_norm")):
            out.append(
                compare(
                    name, f"{prefix}_{key}", _stack(res, field, cameras), case[f"{prefix}_{key}"], rel_to_max=REL_TO_MAX
                )
            )
    if "gc_replay_chunk_score" in case:
        n = int(case.get("num_decoded_steps", generated.shape[1]))
        res = pi0_fast_maps.gradcam_for_chunk(model, obs, generated, list(range(n)))
        out.append(compare(name, "gc_replay_chunk_score", res.score, case["gc_replay_chunk_score"], atol=ATOL["score"]))
        for field, key in (("alphas", "alpha"), ("maps", "cam"), ("grad_norms", "grad_norm")):
            out.append(
                compare(
                    name,
                    f"gc_replay_chunk_{key}",
                    _stack(res, field, cameras),
                    case[f"gc_replay_chunk_{key}"],
                    rel_to_max=REL_TO_MAX,
                )
            )
    return out


def run_golden(folder: str | pathlib.Path, *, verbose: bool = True, scan: bool | None = None) -> list[Comparison]:
    """Every comparison of a golden folder; `scan` forces the layer-stack layout (None: the read-back default)."""
    folder = pathlib.Path(folder)
    config = json.loads((folder / "config.json").read_text())
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
    case_files = sorted(folder.glob("case_*.npz"))
    if not case_files:
        raise FileNotFoundError(f"no case_*.npz files in {folder}")
    results: list[Comparison] = []
    for path in case_files:
        with np.load(path, allow_pickle=False) as npz:
            case = {k: npz[k] for k in npz.files}
        for comp in check_case(model, path.stem, case, cameras, max_steps):
            results.append(comp)
            if verbose:
                print(comp.line(), flush=True)
    return results


def check_folder(folder: pathlib.Path) -> int:
    """Prints every comparison of a golden folder and a verdict line; the exit status (1 on any mismatch or
    unreadable input)."""
    try:
        results = run_golden(folder)
    except Exception as e:  # unreadable input is a failure of the check, reported in one line
        print(f"FAIL cannot check {folder}: {type(e).__name__}: {e}")
        return 1
    failed = [r for r in results if not r.ok]
    print(f"{len(results) - len(failed)} passed, {len(failed)} failed")
    return 1 if failed else 0


if __name__ == "__main__":
    if len(sys.argv) != 2:
        print("usage: python -m openpi_cam.golden DIR", file=sys.stderr)
        raise SystemExit(2)
    raise SystemExit(check_folder(pathlib.Path(sys.argv[1])))
