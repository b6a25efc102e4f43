"""LeRobot's policy-level goldens: LeRobot's own pipelines and policy run on a LeRobot policy folder
(`shared/golden/lerobot_pi05_tiny`, `lerobot_pi0_tiny`), compared with ours under the relative criteria of
`openpi_cam.golden` (`openpi-cam golden FOLDER` dispatches here for such folders)."""

from __future__ import annotations

import pathlib

import numpy as np

from openpi_cam import golden
from openpi_cam.errors import load_json
from openpi_cam.lerobot.policy import OBS_STATE, TASK, TOKEN_MASK, TOKENS, LeRobotParts, build_lerobot
from openpi_cam.policies.checkpoint_format import CONFIG_FILE
from openpi_cam.policies.policy import Policy

LEROBOT_CASES = "cases.npz"


def is_lerobot_golden(folder: pathlib.Path) -> bool:
    if not (folder / LEROBOT_CASES).is_file() or not (folder / CONFIG_FILE).is_file():
        return False
    config = load_json(folder / CONFIG_FILE, object)
    return isinstance(config, dict) and config.get("type") is not None


def _text(case: str, name: str, got: str, want: str) -> golden.Comparison:
    ok = got == want
    return golden.Comparison(case, name, max_abs=0.0 if ok else 1.0, scale=1.0, bound=0.0, ok=ok, note="(exact text)")


def _request(d: dict[str, np.ndarray], cameras: tuple[str, ...], prefix: str = "input/") -> dict[str, object]:
    """The request a LeRobot golden frame's input arrays (under `prefix`) make: its cameras, state and task."""
    obs: dict[str, object] = {c: d[prefix + c] for c in (*cameras, OBS_STATE)}
    obs[TASK] = str(d[prefix + TASK])
    return obs


def check_lerobot_case(
    parts: LeRobotParts, policy: Policy, name: str, d: dict[str, np.ndarray], rel: float
) -> list[golden.Comparison]:
    """One frame of a LeRobot golden (`d`: its arrays without the batch axis): LeRobot's preprocessed request, the
    model's inputs and the normalised and post-processed chunks for the frame's noise; the frame also served as the
    uint8 [H, W, 3] it was made from gives the same model images."""
    cameras = parts.config.real_cameras
    obs = _request(d, cameras)
    pre = obs
    for transform in parts.preprocessor:
        pre = transform(pre)
    response, trace = policy.infer_traced(obs, noise=d["noise"])
    o = trace.observation
    exact = {
        f"pre/{OBS_STATE}": pre[OBS_STATE],
        f"pre/{TOKENS}": np.asarray(o.tokenized_prompt)[0],
        f"pre/{TOKEN_MASK}": np.asarray(o.tokenized_prompt_mask)[0],
        "model/image_masks": [bool(np.asarray(o.image_masks[c])[0]) for c in cameras],
    }
    if "model/state_padded" in d:  # pi0 reads the state through state_proj
        exact["model/state_padded"] = np.asarray(o.state)[0]
    out = [golden.compare(name, key, got, d[key], exact=True) for key, got in exact.items()]
    out.append(_text(name, "pre/task", pre[TASK], str(d["pre/task"])))
    uint8_trace = policy.infer_traced(obs | {c: d[f"input_uint8_hwc/{c}"] for c in cameras}, noise=d["noise"])[1]
    for camera in cameras:
        image = np.moveaxis(np.asarray(o.images[camera])[0], -1, 0)
        want = d[f"model/{camera}"]
        out.append(golden.compare(name, f"model/{camera}", image, want, rel=golden.LEROBOT_IMAGE_REL))
        from_uint8 = np.asarray(uint8_trace.observation.images[camera])
        out.append(golden.compare(name, f"uint8 input {camera}", from_uint8, np.asarray(o.images[camera]), exact=True))
    action_dim = parts.config.action_dim
    out += [
        golden.compare(name, "action_normalized_padded", trace.output, d["action_normalized_padded"], rel=rel),
        golden.compare(name, "action_normalized", trace.output[:, :action_dim], d["action_normalized"], rel=rel),
        golden.compare(name, "action", response["actions"], d["action"], rel=rel),
    ]
    return out


def run_lerobot_golden(folder: pathlib.Path, verbose: bool = True) -> list[golden.Comparison]:
    """Every frame of a LeRobot golden folder (the batch's rows each served alone), and the gradient of its fixed
    linear function of the first frame's chunk w.r.t. the first camera's model-space image."""
    parts = build_lerobot(folder, dtype="float32")
    policy = parts.policy()
    arrays = golden.read_npz(folder / LEROBOT_CASES)
    variation = golden.lerobot_variation(
        arrays["meta/batch2_row_vs_single_maxdiff"], arrays["batch2/action_normalized"]
    )
    rel = golden.SAFETY * variation
    cases = sorted({k.split("/", 1)[0] for k in arrays} - {"grad", "meta"})
    results = []
    for case in cases:
        d = {k[len(case) + 1 :]: v for k, v in arrays.items() if k.startswith(case + "/")}
        rows = d["noise"].shape[0]
        batched_inputs = d[f"input/{OBS_STATE}"].ndim == 2  # single frames' inputs have no batch axis
        for row in range(rows):
            frame = {k: v[row] if batched_inputs or not k.startswith("input") else v for k, v in d.items()}
            name = case if rows == 1 else f"{case}[{row}]"
            results += golden.report(check_lerobot_case(parts, policy, name, frame, rel), verbose)
    results += golden.report(_check_gradient(parts, policy, arrays, rel), verbose)
    return results


def _check_gradient(
    parts: LeRobotParts, policy: Policy, arrays: dict[str, np.ndarray], rel: float
) -> list[golden.Comparison]:
    cameras = parts.config.real_cameras
    obs = _request(arrays, cameras, "case0/input/")
    noise = arrays["case0/noise"][0]
    trace = policy.infer_traced(obs, noise=noise)[1]
    value, grad = golden.flow_image_gradient(parts.model, trace.observation, noise[None], arrays["grad/W"], cameras[0])
    want = arrays["grad/d_objective_d_model_image0"]
    return [
        golden.compare("grad", "objective", value, arrays["grad/objective"], rel=rel),
        golden.compare("grad", "d_objective_d_model_image0", np.moveaxis(grad, -1, 1), want,
                       rel=golden.GRADIENT_AMPLIFICATION * rel),
    ]  # fmt: skip
