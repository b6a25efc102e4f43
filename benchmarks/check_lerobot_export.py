"""Does LeRobot itself accept and run what `openpi-cam export --to lerobot` writes? A check in two environments.

`write DIR` (this project's environment, no torch): exports the bundled pi0.5 demo (`demo_reach_pi05`) to DIR/folder
and records, for a few demo observations and fixed noises, the inputs as a LeRobot dataset gives them (float
[3, H, W] frames, the state, the task), the tokens and the post-processed chunk openpi-cam serves from that folder,
and the chunk the original orbax checkpoint serves (DIR/cases.npz).

`check DIR` (a LeRobot 0.6.1 environment with torch; imports nothing of openpi-cam): loads DIR/folder with LeRobot's
own `PI05Policy.from_pretrained` and `make_pre_post_processors(pretrained_path=...)`, with the folder's sizes record
(`golden_meta.json`) substituted into LeRobot's variant table at run time as the shared LeRobot goldens describe
(LeRobot only knows gemma_2b / gemma_300m and PaliGemma's SigLIP), checks that every weight was loaded (LeRobot's
loader swallows a failed load), runs each case through LeRobot's preprocessor, `predict_action_chunk(noise=...)` and
postprocessor, and prints the largest differences from openpi-cam's tokens and chunks.

    .venv/bin/python benchmarks/check_lerobot_export.py write /tmp/lerobot_export_check
    HF_HUB_OFFLINE=1 /work/lerobot-env/bin/python benchmarks/check_lerobot_export.py check /tmp/lerobot_export_check

CI has no torch, so only `write` runs there (tests/policies/test_lerobot_export.py checks the folder with our reader).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

CASES = 4


def write(out: Path) -> None:
    from openpi_cam.checkpoints import model_spec
    from openpi_cam.demo import bundled, task
    from openpi_cam.lerobot.export import export_lerobot
    from openpi_cam.lerobot.policy import create_lerobot_policy
    from openpi_cam.policies import demo_reach

    folder = export_lerobot(
        demo_reach.ASSETS_PI05 / demo_reach.CHECKPOINT.name,
        demo_reach.DEMO_PI05_CONFIG,
        out / "folder",
        paligemma_tokenizer=demo_reach.ASSETS_PI05 / demo_reach.PALIGEMMA_TOKENIZER.name,
    )
    ours = create_lerobot_policy(folder, dtype="float32")
    original = model_spec.create_demo_policy("pi05", dtype="float32")
    rng = np.random.default_rng(0)
    arrays: dict[str, np.ndarray] = {}
    for i in range(CASES):
        scene_rng = np.random.default_rng(100 + i)
        scene = task.random_scene(scene_rng)
        obs = bundled.policy_input(bundled.client_observation(task.observe(scene, task.random_start(scene_rng, scene))))
        noise = rng.standard_normal((demo_reach.ACTION_HORIZON, 32)).astype(np.float32)
        request = {demo_reach.LEROBOT_KEYS[k]: v for k, v in obs.items() if k in demo_reach.LEROBOT_KEYS}
        request = {k: np.moveaxis(v, -1, 0).astype(np.float32) / 255 if v.ndim == 3 else np.asarray(v, np.float32)
                   for k, v in request.items()}  # fmt: skip
        response, trace = ours.infer_traced(request | {"task": obs["prompt"]}, noise=noise)
        arrays |= {f"case{i}/input/{k}": v for k, v in request.items()}
        arrays[f"case{i}/task"] = np.asarray(obs["prompt"])
        arrays[f"case{i}/noise"] = noise
        arrays[f"case{i}/tokens"] = np.asarray(trace.observation.tokenized_prompt)[0]
        arrays[f"case{i}/actions"] = response["actions"]
        arrays[f"case{i}/original_actions"] = original.infer(obs, noise=noise)["actions"]
    np.savez(out / "cases.npz", **arrays)
    print(f"exported {folder} and recorded {CASES} cases in {out / 'cases.npz'}")


def substitute_sizes(folder: Path) -> None:
    """LeRobot builds a pi0.5 of its two variants only: give its variant table and Hugging Face configs the folder's
    recorded sizes while the model is constructed."""
    import lerobot.policies.pi05.modeling_pi05 as modeling

    record = json.loads((folder / "golden_meta.json").read_text())
    tiny, vocab = record["tiny"], record["vocab_size"]
    sizes = {"gemma_2b": tiny["vlm"], "gemma_300m": tiny["expert"]}
    modeling.get_gemma_config = lambda variant: modeling.GemmaConfig(**sizes[variant])
    paligemma, expert = modeling.PaliGemmaForConditionalGenerationWithPiGemma, modeling.PiGemmaForCausalLM

    def build_paligemma(config):
        config.text_config.vocab_size = vocab
        for name, value in tiny["siglip"].items():
            if name != "image_size":  # LeRobot sets it from the config's image_resolution
                setattr(config.vision_config, name, value)
        return paligemma(config=config)

    def build_expert(config):
        config.vocab_size = vocab
        return expert(config=config)

    modeling.PaliGemmaForConditionalGenerationWithPiGemma = build_paligemma
    modeling.PiGemmaForCausalLM = build_expert


def check(out: Path) -> int:
    import torch
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.pi05.modeling_pi05 import PI05Policy
    from safetensors.torch import load_file

    folder = out / "folder"
    substitute_sizes(folder)
    torch.set_num_threads(1)
    policy = PI05Policy.from_pretrained(str(folder))
    policy.eval()
    stored = load_file(str(folder / "model.safetensors"))
    loaded = policy.state_dict()
    mismatched = [k for k, v in stored.items() if k not in loaded or not torch.equal(loaded[k], v)]
    missing = [k for k in loaded if k not in stored]
    print(f"weights: {len(stored)} tensors in the file, {len(mismatched)} not loaded as stored, {len(missing)} "
          f"of the module's missing from the file")  # fmt: skip
    tokenizer = {"tokenizer_processor": {"tokenizer_name": str(folder / "tokenizer")}}
    pre, post = make_pre_post_processors(policy.config, pretrained_path=str(folder), preprocessor_overrides=tokenizer)
    with np.load(out / "cases.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    worst, worst_original, tokens_equal = 0.0, 0.0, True
    for i in range(CASES):
        frame = {k.split("/", 2)[2]: torch.from_numpy(v) for k, v in arrays.items() if k.startswith(f"case{i}/input/")}
        batch = pre(frame | {"task": str(arrays[f"case{i}/task"])})
        tokens = batch["observation.language.tokens"][0].numpy()
        tokens_equal &= bool(np.array_equal(tokens, arrays[f"case{i}/tokens"]))
        with torch.no_grad():
            chunk = policy.predict_action_chunk(batch, noise=torch.from_numpy(arrays[f"case{i}/noise"])[None])
        actions = post(chunk)[0].numpy()
        scale = np.abs(arrays[f"case{i}/actions"]).max()
        worst = max(worst, float(np.abs(actions - arrays[f"case{i}/actions"]).max() / scale))
        worst_original = max(worst_original, float(np.abs(actions - arrays[f"case{i}/original_actions"]).max() / scale))
        print(f"case{i}: LeRobot's chunk {actions.shape}, max |LeRobot - openpi-cam's LeRobot folder| / max|chunk| "
              f"{np.abs(actions - arrays[f'case{i}/actions']).max() / scale:.2e}, vs the original orbax checkpoint "
              f"{np.abs(actions - arrays[f'case{i}/original_actions']).max() / scale:.2e}")  # fmt: skip
    print(f"tokens equal to openpi-cam's: {tokens_equal}; worst relative difference {worst:.2e} (folder), "
          f"{worst_original:.2e} (original)")  # fmt: skip
    return 0 if tokens_equal and not mismatched and not missing else 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=("write", "check"))
    parser.add_argument("dir", type=Path)
    args = parser.parse_args()
    args.dir.mkdir(parents=True, exist_ok=True)
    if args.mode == "write":
        write(args.dir)
        return 0
    return check(args.dir)


if __name__ == "__main__":
    sys.exit(main())
