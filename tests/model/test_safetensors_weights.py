"""pi0 / pi0.5 weights in PyTorch's layout, without torch: OpenPI trees written and read back bit for bit (LeRobot's
`model.` keys and OpenPI's export's bare keys, float32 and bfloat16), LeRobot's own file read with the architecture
its shapes and sizes record describe, `lm_head` standing in for a missing `embed_tokens`, every bad tensor refused in
one line naming it, and the peak memory of loading within 1.25x the file (a fresh process, the benchmark's own
measurement). That the mapping is LeRobot's (not merely self-consistent) is shown by LeRobot's goldens
(tests/policies/test_lerobot_policy.py): its chunks and gradients follow from these weights.
"""

from __future__ import annotations

import json
import subprocess
import sys

import ml_dtypes
import numpy as np
import pytest
from paths import GOLDEN_DIR, REPO_ROOT
from safetensors_edit import edit_safetensors, read_tensor

from openpi_cam.model.pi0 import Pi0
from openpi_cam.model.safetensors_weights import (
    HeadCounts,
    load_safetensors_params,
    read_tensor_infos,
    save_safetensors_params,
    torch_shapes,
)
from openpi_cam.nested import flatten_dict

LEROBOT = GOLDEN_DIR / "lerobot_pi05_tiny"
WEIGHTS = LEROBOT / "model.safetensors"
EMBED = "model.paligemma_with_expert.paligemma.model.language_model.embed_tokens.weight"
LM_HEAD = "model.paligemma_with_expert.paligemma.lm_head.weight"
Q_PROJ = "model.paligemma_with_expert.gemma_expert.model.layers.1.self_attn.q_proj.weight"


def golden_heads() -> HeadCounts:
    tiny = json.loads((LEROBOT / "golden_meta.json").read_text())["tiny"]
    return HeadCounts(gemma=tiny["vlm"]["num_heads"], siglip=tiny["siglip"]["num_attention_heads"])


@pytest.mark.parametrize("family", ["tiny_pi0", "tiny_pi05"])
def test_openpi_trees_round_trip_through_the_pytorch_layout(tmp_path, family):
    model = Pi0.from_checkpoint(GOLDEN_DIR / family / "checkpoint" / "params", dtype="float32")
    cfg = model.config
    heads = HeadCounts(gemma=cfg.gemma.num_heads, siglip=cfg.siglip.num_heads)
    want = {k: np.asarray(v) for k, v in flatten_dict(model.params).items()}
    for prefix in ("model.", ""):
        for dtype in ("float32", "bfloat16"):
            path = save_safetensors_params(tmp_path / f"{prefix}{dtype}.safetensors", model.params, cfg,
                                           prefix=prefix, dtype=dtype)  # fmt: skip
            assert all(k.startswith(prefix) for k in read_tensor_infos(path))
            params, arch = load_safetensors_params(path, heads=heads)
            got = flatten_dict(params)
            assert got.keys() == want.keys()
            for key, value in got.items():
                value = np.asarray(value)
                assert value.dtype == np.dtype(ml_dtypes.bfloat16 if dtype == "bfloat16" else np.float32), key
                np.testing.assert_array_equal(value, want[key].astype(value.dtype), err_msg=key)
            assert (arch.gemma, arch.expert, arch.siglip, arch.pi05) == (cfg.gemma, cfg.expert, cfg.siglip, cfg.pi05)


def test_lerobots_file_reads_its_architecture_and_every_tensor():
    params, cfg = load_safetensors_params(WEIGHTS, dtype="float32", heads=golden_heads())
    meta = json.loads((LEROBOT / "golden_meta.json").read_text())
    tiny = meta["tiny"]
    for ours, theirs in ((cfg.gemma, tiny["vlm"]), (cfg.expert, tiny["expert"])):
        assert {k: getattr(ours, k) for k in theirs} == theirs
    siglip = tiny["siglip"]
    assert (cfg.siglip.width, cfg.siglip.depth, cfg.siglip.num_heads, cfg.siglip.mlp_dim) == (
        siglip["hidden_size"], siglip["num_hidden_layers"], siglip["num_attention_heads"], siglip["intermediate_size"]
    )  # fmt: skip
    assert (cfg.gemma.vocab_size, cfg.pi05, cfg.action_dim, cfg.siglip.image_size) == (
        meta["vocab_size"],
        True,
        32,
        224,
    )
    # The layout of that architecture is the file's key set, the two LM heads the policy never reads aside.
    infos = read_tensor_infos(WEIGHTS)
    expected = torch_shapes(cfg)
    assert {k: infos[k].shape for k in expected} == expected
    assert set(infos) - set(expected) == {LM_HEAD, "model.paligemma_with_expert.gemma_expert.lm_head.weight"}
    flat = flatten_dict(params)
    q = read_tensor(WEIGHTS, Q_PROJ)  # [heads x head_dim, width] -> [heads, width, head_dim]
    expert_q = np.asarray(flat["PaliGemma/llm/layers/attn/q_einsum_1/w"])[1]
    np.testing.assert_array_equal(expert_q, q.reshape(cfg.expert.num_heads, cfg.expert.head_dim, -1).transpose(0, 2, 1))


def test_bfloat16_files_load_as_stored_or_cast(tmp_path):
    bf16 = edit_safetensors(WEIGHTS, tmp_path / "bf16.safetensors", dtype="bfloat16")
    assert {info.dtype for info in read_tensor_infos(bf16).values()} == {"BF16"}
    reference, _ = load_safetensors_params(WEIGHTS, heads=golden_heads())
    stored, _ = load_safetensors_params(bf16, heads=golden_heads())
    upcast, _ = load_safetensors_params(bf16, dtype="float32", heads=golden_heads())
    for key, value in flatten_dict(reference).items():
        rounded = np.asarray(value).astype(ml_dtypes.bfloat16)
        np.testing.assert_array_equal(np.asarray(flatten_dict(stored)[key]), rounded, err_msg=key)
        np.testing.assert_array_equal(np.asarray(flatten_dict(upcast)[key]), rounded.astype(np.float32), err_msg=key)
    assert np.asarray(flatten_dict(stored)["time_mlp_in/kernel"]).dtype == ml_dtypes.bfloat16


def test_lm_head_stands_in_for_a_missing_embedding_and_embed_tokens_wins_otherwise(tmp_path):
    embedding = read_tensor(WEIGHTS, EMBED)
    only_head = edit_safetensors(WEIGHTS, tmp_path / "head.safetensors", drop=(EMBED,))
    params, _ = load_safetensors_params(only_head, heads=golden_heads())
    np.testing.assert_array_equal(np.asarray(params["PaliGemma"]["llm"]["embedder"]["input_embedding"]), embedding)
    other_head = edit_safetensors(WEIGHTS, tmp_path / "other.safetensors", replace={LM_HEAD: embedding + 1})
    params, _ = load_safetensors_params(other_head, heads=golden_heads())
    np.testing.assert_array_equal(np.asarray(params["PaliGemma"]["llm"]["embedder"]["input_embedding"]), embedding)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        ({"drop": (Q_PROJ,)}, f"missing tensor '{Q_PROJ}' \\(expected shape \\[128, 32\\]\\)"),
        ({"add": {"model.extra.weight": np.zeros(3, np.float32)}}, "unexpected tensor 'model.extra.weight'"),
        (
            {"replace": {Q_PROJ: np.zeros((128, 31), np.float32)}},
            f"tensor '{Q_PROJ}' has shape \\[128, 31\\], expected",
        ),
        (
            {"rename": lambda k: k[len("model.") :] if k.startswith("model.time") else k},
            "key 'time_mlp_in.bias' breaks",
        ),
        ({"drop": (EMBED, LM_HEAD)}, f"missing tensor '{LM_HEAD}'"),
    ],
)
def test_bad_tensors_are_refused_in_one_line_naming_them(tmp_path, edit, message):
    bad = edit_safetensors(WEIGHTS, tmp_path / "bad.safetensors", **edit)
    with pytest.raises(ValueError, match=message) as raised:
        load_safetensors_params(bad, heads=golden_heads())
    assert "\n" not in str(raised.value) and str(bad) in str(raised.value)


def test_a_siglip_head_count_the_weights_cannot_show_is_asked_for():
    with pytest.raises(ValueError, match="SigLIP width 32 is not PaliGemma's") as raised:
        load_safetensors_params(WEIGHTS)
    assert "\n" not in str(raised.value)


def test_loading_peak_memory_is_within_a_quarter_above_the_file():
    """The benchmark's measurement (benchmarks/bench_lerobot_weights.py) at its small size, in a fresh process: the
    resident high-water mark grows by at most 1.25x the file while loading. Holding the file's mapped pages until the
    end, or a host copy beside each device array (an unaligned buffer that XLA copies), lands above it."""
    script = REPO_ROOT / "benchmarks" / "bench_lerobot_weights.py"
    out = subprocess.run([sys.executable, str(script), "--size", "small", "--json"], capture_output=True, text=True,
                         check=True, timeout=300)  # fmt: skip
    figures = json.loads(out.stdout.strip().splitlines()[-1])
    assert figures["file_bytes"] > 300e6
    peak = figures["peak_growth"] / figures["file_bytes"]
    assert peak <= 1.25, f"loading {figures['file_bytes'] / 1e6:.0f} MB peaked at {peak:.2f}x the file"
    assert figures["resident_growth"] >= 0.95 * figures["file_bytes"]  # the weights themselves are resident
