"""pi0 and pi0.5 against upstream's goldens: embeddings, every Euler iterate, actions, the training loss, and the
gradients of the actions with respect to the image tokens (through the whole denoising loop).

Tolerances (float32): values within REL of the reference's largest magnitude, gradients and their reductions within
GRAD_REL of theirs (`golden.FLOW_REL` / `golden.FLOW_GRAD_REL`, where the reasoning is), time steps exactly. A masked
camera's gradient must be exactly zero, as upstream's.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from paths import GOLDEN_DIR

from openpi_cam import golden
from openpi_cam.model import pi0
from openpi_cam.model.attribution import region_map, region_masks
from openpi_cam.model.checkpoint import read_param_shapes
from openpi_cam.model.config import check_param_tree, family_of, pi0_param_shapes
from openpi_cam.model.observation import Observation
from openpi_cam.model.pi0_maps import CHUNK, maps_for_actions, rescore_masks
from openpi_cam.nested import flatten_dict
from openpi_cam.vocabulary import MapOptions

REL = golden.FLOW_REL
GRAD_REL = golden.FLOW_GRAD_REL
CAMERAS = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")
FAMILIES = {"pi0": "tiny_pi0", "pi05": "tiny_pi05"}


def assert_close(got, want, rel: float, what: str) -> None:
    """The golden criterion (`golden.compare`): max |got - want| <= rel x max |want|."""
    comparison = golden.compare("", what, got, want, rel=rel)
    assert comparison.ok, comparison.line()


@functools.cache
def load_model(family: str) -> pi0.Pi0:
    folder = GOLDEN_DIR / FAMILIES[family]
    data_cfg = json.loads((folder / "config.json").read_text())["pi0_config"]
    return pi0.Pi0.from_checkpoint(
        folder / "checkpoint" / "params",
        dtype="float32",
        action_horizon=data_cfg["action_horizon"],
        max_token_len=data_cfg["max_token_len"],
    )


def load_case(family: str, name: str) -> tuple[dict, Observation]:
    with np.load(GOLDEN_DIR / FAMILIES[family] / f"{name}.npz") as npz:
        d = {k: npz[k] for k in npz.files}
    obs = Observation(
        images={c: d[f"image_{c}"] for c in CAMERAS},
        image_masks={c: d[f"image_mask_{c}"] for c in CAMERAS},
        state=d["state"],
        tokenized_prompt=d["tokenized_prompt"],
        tokenized_prompt_mask=d["tokenized_prompt_mask"],
    )
    return d, obs


@pytest.mark.parametrize("family", ["pi0", "pi05"])
def test_architecture_and_family_read_from_the_checkpoint(family):
    model = load_model(family)
    assert model.family == family and model.config.pi05 == (family == "pi05")
    shapes = read_param_shapes(GOLDEN_DIR / FAMILIES[family] / "checkpoint" / "params")
    assert family_of(shapes) == family
    check_param_tree(shapes, pi0_param_shapes(model.config))
    assert (model.config.gemma.width, model.config.expert.width, model.config.expert.depth) == (64, 32, 2)


@pytest.mark.parametrize(
    "name", ["pi0_param_tree.json", "pi05_param_tree.json", "pi0_lora_param_tree.json", "pi05_lora_param_tree.json"]
)
def test_full_size_trees_equal_upstreams(name):
    """The tree our config builds (through `jax.eval_shape` of our initialiser, no weights) is upstream's."""
    leaves = json.loads((GOLDEN_DIR / "param_trees" / name).read_text())["leaves"]
    upstream = {k: tuple(v["shape"]) for k, v in leaves.items()}
    gemma, expert, siglip, pi05 = pi0.pi0_architecture_from_params(upstream)
    cfg = pi0.Pi0Config(gemma, expert, siglip, pi05)
    ours = flatten_dict(jax.eval_shape(functools.partial(pi0.init_params, cfg), jax.random.key(0)))
    assert {k: tuple(v.shape) for k, v in ours.items()} == upstream
    assert (expert.width, expert.depth, expert.lora_rank) == (1024, 18, 32 if "lora" in name else 0)


def test_the_model_reads_its_own_camera_set_in_its_order():
    """`Pi0Config.image_keys` is the model's camera set: upstream's three under other names give upstream's actions
    exactly; another order is another token order (other actions); a camera the set names must be sent."""
    model = load_model("pi05")
    d, obs = load_case("pi05", "case_a")
    new_names = ("observation.images.front", "observation.images.left", "observation.images.right")
    names = dict(zip(CAMERAS, new_names, strict=True))
    renamed = dataclasses.replace(
        obs,
        images={names[c]: v for c, v in obs.images.items()},
        image_masks={names[c]: v for c, v in obs.image_masks.items()},
    )

    def actions(image_keys: tuple[str, ...], observation: Observation) -> np.ndarray:
        cfg = dataclasses.replace(model.config, image_keys=image_keys)
        return np.asarray(pi0.sample_actions_jit(model.params, observation, jnp.asarray(d["noise"]), cfg=cfg))

    upstream = np.asarray(model.sample_actions(jax.random.key(0), obs, noise=d["noise"]))
    np.testing.assert_array_equal(actions(tuple(names.values()), renamed), upstream)
    swapped = tuple(names[c] for c in (CAMERAS[1], CAMERAS[0], CAMERAS[2]))
    assert np.abs(actions(swapped, renamed) - upstream).max() > 1e-3
    with pytest.raises(ValueError, match=r"lacks the camera\(s\) \['base_0_rgb', 'left"):
        actions(CAMERAS, renamed)


def flow_cases(slow_families: tuple[str, ...] = ()) -> list:
    """(family, case) pairs, the slow tier's marked: case_c, the batch of two, compiles programs of its own (the fast
    tier batches flow models in serving/test_batching.py), and so does each family in `slow_families`."""
    return [
        pytest.param(
            family,
            name,
            id=f"{name}-{family}",
            marks=pytest.mark.slow if name == "case_c" or family in slow_families else (),
        )
        for family in ("pi0", "pi05")
        for name in ("case_a", "case_b", "case_c")
    ]


# pi0.5's sampled actions are upstream's in the fast tier too, from a raw observation (policies/test_pi0_policy.py).
@pytest.mark.parametrize(("family", "name"), flow_cases(slow_families=("pi05",)))
def test_sampling_and_loss_match_upstream(family, name):
    model = load_model(family)
    d, obs = load_case(family, name)
    E = model.embed_images(obs)
    for i, c in enumerate(CAMERAS):
        assert_close(E[:, i], d[f"siglip_{c}"], REL, f"siglip {c}")
    actions = model.sample_actions(jax.random.key(0), obs, noise=d["noise"])
    assert_close(actions, d["actions"], REL, "actions")
    prepared = pi0.preprocess(obs, model.config)
    record = jax.jit(functools.partial(pi0.denoise, cfg=model.config, record=True))
    _, (xs, vs, ts) = record(model.params, E, prepared, jnp.asarray(d["noise"]))
    np.testing.assert_array_equal(np.asarray(ts), d["t_steps"][:10])  # float32 time accumulation, exactly
    assert_close(xs, d["x_t_steps"][:, :10], REL, "Euler iterates")
    assert_close(vs, d["v_t_steps"], REL, "velocities")
    loss = model.compute_loss(obs, d["loss_actions"], d["loss_noise"], d["loss_time"])
    assert_close(loss, d["loss"], REL, "loss")


@pytest.mark.parametrize(("family", "name"), flow_cases())
def test_gradients_through_the_denoising_loop_match_upstream(family, name):
    model = load_model(family)
    d, obs = load_case(family, name)
    targets = {"gc_h0_d0": (0, 0), "gc_h0_d6": (0, 6), "gc_h9_d3": (9, 3), "gc_chunk": CHUNK}
    res = maps_for_actions(model, obs, d["noise"], list(targets.values()))
    assert_close(res.actions, d["actions"], REL, "explained actions")
    for t, key in enumerate(targets):
        assert_close(res.score[:, t], d[f"{key}_score"], REL, f"{key} score")
        for field, ours in (("alpha", res.alphas), ("grad_norm", res.grad_norms)):
            got = np.stack([ours[c][:, t] for c in CAMERAS], axis=1)
            assert_close(got, d[f"{key}_{field}"], GRAD_REL, f"{key} {field}")
        cam = np.stack([res.by_kind["gradcam"][c][:, t] for c in CAMERAS], axis=1)
        assert_close(cam, d[f"{key}_cam"], GRAD_REL, f"{key} cam")
        norms = np.stack([res.by_kind["gradnorm"][c][:, t] for c in CAMERAS], axis=1)
        want = np.linalg.norm(d[f"{key}_grad"], axis=-1).reshape(norms.shape)  # per-token norm of upstream's G
        assert_close(norms, want, GRAD_REL, f"{key} gradient norm map")
    if name == "case_b":  # left wrist masked: no gradient reaches it, exactly
        assert not res.grad_norms["left_wrist_0_rgb"].any() and not res.valid["left_wrist_0_rgb"].any()


def test_masked_camera_and_noise_change_the_actions_as_upstream():
    """The pi0 model reads every valid camera and the noise, and ignores a masked camera's pixels exactly."""
    model = load_model("pi0")
    d, obs = load_case("pi0", "case_b")  # left wrist masked
    base = np.asarray(model.sample_actions(None, obs, noise=d["noise"]))
    other = np.random.default_rng(0).uniform(-1, 1, d["image_left_wrist_0_rgb"].shape).astype(np.float32)
    masked_changed = dataclasses.replace(obs, images={**obs.images, "left_wrist_0_rgb": other})
    np.testing.assert_array_equal(np.asarray(model.sample_actions(None, masked_changed, noise=d["noise"])), base)
    valid_changed = dataclasses.replace(obs, images={**obs.images, "base_0_rgb": other})
    assert np.abs(np.asarray(model.sample_actions(None, valid_changed, noise=d["noise"])) - base).max() > 0.1
    assert np.abs(np.asarray(model.sample_actions(None, obs, noise=d["noise"] + 1.0)) - base).max() > 0.1


def test_bad_targets_are_refused_by_name():
    model = load_model("pi0")
    d, obs = load_case("pi0", "case_a")
    with pytest.raises(ValueError, match=r"action \(10, 0\) outside the chunk \[10, 32\]"):
        maps_for_actions(model, obs, d["noise"], [(10, 0)])
    with pytest.raises(ValueError, match="lacks the camera"):
        model.sample_actions(
            jax.random.key(0), dataclasses.replace(obs, images={"base_0_rgb": obs.images["base_0_rgb"]})
        )


@pytest.mark.parametrize("family", ["pi0", pytest.param("pi05", marks=pytest.mark.slow)])
def test_ig_and_occlusion_through_the_denoising_loop(family):
    """The baseline kinds explain the same x_0 as the gradient kinds: IG's attributions add up to score(frame) -
    score(baseline frame) (its completeness check), occlusion is the drop of exactly the re-scoring a user can run
    (`rescore_masks`), and the masked camera gets nothing from either."""
    model = load_model(family)
    d, obs = load_case(family, "case_b")  # batch 1, left wrist masked
    # 2 x 2 regions of 8 x 8 patches: 4 re-runs per camera (each re-runs SigLIP and the whole denoising loop); the
    # region size is not what this test is about, the equality with a user's re-scoring is.
    options = MapOptions(occlusion_region=8)
    targets = [(0, 6), CHUNK]
    res = maps_for_actions(model, obs, d["noise"], targets, kinds=("ig", "occlusion"), options=options)
    assert set(res.by_kind) == {"ig", "occlusion"} and not res.alphas
    assert_close(res.actions, d["actions"], REL, "explained actions without a gradient pass")
    assert_close(res.score[:, 0], d["gc_h0_d6_score"], REL, "score of (0, 6)")
    assert_close(res.score[:, 1], d["gc_chunk_score"], REL, "chunk score")

    check = res.ig_completeness
    gap = check.score - check.baseline_score
    assert np.all(np.abs(gap[:, 1]) > 1.0)  # the baseline frame moves the chunk, so completeness says something
    assert np.all(np.abs(check.attribution_sum - gap) <= options.ig_tolerance * np.maximum(np.abs(gap), 1e-3))
    total = sum(res.by_kind["ig"][c].astype(np.float64).sum(axis=(-2, -1)) for c in CAMERAS)
    np.testing.assert_allclose(total, check.attribution_sum, rtol=1e-5)  # float32 maps summed in float64
    # Drops are differences of float32 scores of magnitude |s| from differently batched programs: 1e-5 |s| (measured
    # differences <= 1e-6 |s|).
    atol = 1e-5 * np.abs(res.score).max()
    assert not res.by_kind["ig"]["left_wrist_0_rgb"].any()  # its tokens are its own baseline: no path, exactly 0
    assert np.abs(res.by_kind["occlusion"]["left_wrist_0_rgb"]).max() <= atol  # painting it changes nothing
    for kind in ("ig", "occlusion"):
        assert np.abs(res.by_kind[kind]["base_0_rgb"]).max() > 100 * atol, kind

    grid = model.config.siglip.grid
    masks = region_masks(grid, options.occlusion_region)
    painted = np.concatenate([np.zeros((1, *grid), bool), masks])
    scores = rescore_masks(model, obs, d["noise"], {"base_0_rgb": painted}, targets, options=options)["base_0_rgb"]
    assert_close(scores[0], res.score, REL, "unpainted re-score")
    expected = region_map(masks, scores[:1] - scores[1:])  # [B, T, Hp, Wp]
    np.testing.assert_allclose(res.by_kind["occlusion"]["base_0_rgb"], expected, rtol=0, atol=atol)


@pytest.mark.parametrize(
    ("folder", "expected"),
    [
        # 3 cases x (3 SigLIP + iterates + velocities + actions + loss + 4 targets x 4 arrays); the comparisons
        # themselves are this file's in-process tests, so the command's own run is slow tier
        pytest.param("tiny_pi0", 69, marks=pytest.mark.slow),
        ("tiny_policy_pi0_libero", 22),  # 2 cases x (2 prompt arrays + 3 images + 3 masks + state + output + actions)
        ("param_trees", 4),  # pi0, pi0.5 and their LoRA variants
    ],
)
def test_golden_command_checks_the_flow_matching_folders(folder, expected):
    """`openpi-cam golden` reads each new golden folder as upstream wrote it and passes on all of its comparisons."""
    done = subprocess.run(
        [sys.executable, "-m", "openpi_cam", "golden", str(GOLDEN_DIR / folder)],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == f"{expected} passed, 0 failed"
