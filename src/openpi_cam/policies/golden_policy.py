"""Policy-level goldens, compared with ours under the relative criteria of `openpi_cam.golden` (`openpi-cam golden
FOLDER` dispatches here for such folders): upstream's `create_trained_policy` + `Policy.infer(obs, noise=...)` from a
raw client observation (`shared/golden/tiny_policy_pi05_droid`, `tiny_policy_pi0_libero`). LeRobot's own pipelines
and policy run on a LeRobot policy folder are `lerobot.golden`'s."""

from __future__ import annotations

import pathlib

import numpy as np

from openpi_cam import golden
from openpi_cam.errors import load_json
from openpi_cam.policies.policy import Policy, create_policy


def is_policy_folder(folder: pathlib.Path) -> bool:
    return (folder / "case.json").is_file() and not (folder / "config.json").is_file()


def check_policy_case(policy: Policy, name: str, d: dict, prompt: str) -> list[golden.Comparison]:
    """One flow-matching policy golden case (`tiny_policy_*`): the raw client observation through our transforms
    gives upstream's model inputs exactly, and with the case's noise upstream's model output and actions."""
    obs = {"observation/" + k[len("raw/") :]: v for k, v in d.items() if k.startswith("raw/")} | {"prompt": prompt}
    response, trace = policy.infer_traced(obs, noise=d["noise"])
    o = trace.observation
    exact = {key: np.asarray(getattr(o, key))[0] for key in ("tokenized_prompt", "tokenized_prompt_mask")}
    for camera, image in o.images.items():
        exact[f"image/{camera}"] = np.round((np.asarray(image)[0] + 1.0) / 2.0 * 255.0)  # the uint8 model input
        exact[f"image_mask/{camera}"] = np.asarray(o.image_masks[camera]).reshape(-1)[0]
    close = {"state": np.asarray(o.state)[0], "model_output/actions": trace.output}
    out = [golden.compare(name, key, got, d[f"model_input/{key}"], exact=True) for key, got in exact.items()]
    out += [
        golden.compare(name, key, got, d[key if "/" in key else f"model_input/{key}"], rel=golden.FLOW_REL)
        for key, got in close.items()
    ]
    out.append(golden.compare(name, "actions", response["actions"], d["policy_output/actions"], rel=golden.FLOW_REL))
    return out


def run_policy_golden(folder: pathlib.Path, verbose: bool = True) -> list[golden.Comparison]:
    """Every case of a policy golden folder, served by the config the folder names, float32 as its reference."""
    info = load_json(folder / "case.json")
    policy = create_policy(
        info["config_name"],
        folder / "checkpoint",
        paligemma_tokenizer=folder / "paligemma_tokenizer_tiny.model",
        dtype="float32",
    )
    results = []
    for name, case in golden.read_cases(folder):
        results += golden.report(check_policy_case(policy, name, case, info["cases"][name]["prompt"]), verbose)
    return results
