"""The occlusion head (`model.occlusion_head`) and its fit (`maps.head_fit`, `openpi-cam head fit`) on synthetic maps
datasets written in the real format, whose relation between the input kinds and occlusion is planted: the fitted head
must find it on held-out episodes, where an input alone cannot. Its file round-trips to the same maps, and a file that
cannot be trusted is refused in one line."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from one_line import assert_one_line

from openpi_cam import cli
from openpi_cam.maps import dataset as fmt
from openpi_cam.maps.head_fit import HeadFitOptions, fit, read_examples, split
from openpi_cam.model import occlusion_head
from openpi_cam.vocabulary import OCCLUSION_HEAD, ExplainOptions, HeadRef

CAMERAS = ("base_0_rgb", "wrist_0_rgb")
GRID = (4, 4)
N = GRID[0] * GRID[1]
# The planted target's noise, in units of the camera's largest |value|: small beside the gap between the largest and
# second-largest of 16 normal draws in nearly every example (at 0.02 it swapped them in 3 of 25), so occlusion's top
# patch is the planted one's.
NOISE = 0.005
# A fit this small must still come out right: 20 episodes of 5 frames, a quarter held out (25 maps per camera).
EPISODES, FRAMES = 20, 5
OPTIONS = HeadFitOptions(inputs=("gradnorm", "lrp"), hidden=8, steps=1500)


def _write(root: Path, planted, seed: int = 0, model: dict | None = None) -> Path:
    """A maps dataset of random gradnorm and lrp maps, each camera's of its own random scale (the head must read
    shapes, not scales), and occlusion = planted(camera index, gradnorm, lrp) + noise. One camera is masked in some
    frames (such maps must not be fitted on)."""
    info = fmt.MapsInfo(
        source="synthetic",
        source_version="v3.0",
        source_fps=10.0,
        model=model or {"config": "demo_reach"},
        family="pi0_fast",
        target="action-token",
        kinds=["gradnorm", "lrp", "occlusion"],
        grids={c: list(GRID) for c in CAMERAS},
        camera_sources={c: c for c in CAMERAS},
        keys={},
        options={},
    )
    fmt.write_json(root / fmt.INFO_JSON, info.to_json())
    rng = np.random.default_rng(seed)
    for e in range(EPISODES):
        rows = []
        for f in range(FRAMES):
            row = {"index": e * FRAMES + f, "episode_index": e, "frame_index": f}
            row[fmt.CAMERAS_COLUMN] = json.dumps({c: {"valid": not (c == CAMERAS[1] and f == 4)} for c in CAMERAS})
            for i, camera in enumerate(CAMERAS):
                gradnorm = np.abs(rng.normal(size=N)) * 10 ** rng.uniform(-3, 1)
                lrp = rng.normal(size=N) * 10 ** rng.uniform(-3, 1)
                target = planted(i, gradnorm / gradnorm.max(), lrp / np.abs(lrp).max()) + NOISE * rng.normal(size=N)
                for kind, m in (("gradnorm", gradnorm), ("lrp", lrp), ("occlusion", target * 10 ** rng.uniform(-2, 1))):
                    row[fmt.map_column(kind, camera)] = m.astype(np.float32).tolist()
            rows.append(row)
        fmt.write_shard(root, info, e, rows)
    return root


def _sign_by_camera(camera: int, gradnorm: np.ndarray, lrp: np.ndarray) -> np.ndarray:
    """Occlusion follows lrp on the first camera and its opposite on the second: the head must read the camera."""
    return lrp if camera == 0 else -lrp


def _figures(head: occlusion_head.OcclusionHead, camera: str) -> dict:
    return head.fit["figures"]["held_out"]["by_camera"][camera]


@pytest.fixture(scope="module")
def planted(tmp_path_factory) -> tuple[Path, occlusion_head.OcclusionHead]:
    root = _write(tmp_path_factory.mktemp("planted") / "synthetic.maps", _sign_by_camera)
    return root, fit([root], OPTIONS)


def test_the_head_finds_a_planted_relation_on_held_out_episodes(planted):
    _, head = planted
    record = head.fit
    assert len(record["held_out_episodes"]) == round(0.25 * EPISODES)
    # masked wrist frames are not examples: one per episode
    assert sum(record["examples"].values()) == EPISODES * (2 * FRAMES - 1)
    for camera in CAMERAS:
        figures = _figures(head, camera)
        assert figures["head"]["top1"] >= 0.9, (camera, figures)
        assert figures["head"]["spearman_median"] >= 0.9, (camera, figures)
        assert figures["inputs"]["gradnorm"]["top1"] <= 0.3  # unrelated: chance is 1 in 16
        assert figures["prior"]["top1"] <= 0.3  # occlusion falls anywhere: where it tends to fall says little
    # lrp alone is right on one camera (as right as the noise lets anything be: the head matches it there) and ranks
    # the other upside down
    assert _figures(head, CAMERAS[0])["head"]["top1"] >= _figures(head, CAMERAS[0])["inputs"]["lrp"]["top1"] >= 0.9
    assert _figures(head, CAMERAS[1])["inputs"]["lrp"]["top1"] <= 0.1
    assert _figures(head, CAMERAS[1])["inputs"]["lrp"]["spearman_median"] <= -0.9
    assert "not measured offline" in record["figures"]["deletion"]
    assert head.model == {"config": "demo_reach"} and head.target == "action-token" and head.family == "pi0_fast"


def test_the_position_bias_learns_where_occlusion_falls(tmp_path):
    """Inputs that say nothing and an occlusion peak at one patch per camera: only the per-position bias can
    place it."""
    peaks = (5, 10)

    def at_a_fixed_patch(camera: int, gradnorm: np.ndarray, lrp: np.ndarray) -> np.ndarray:
        return np.eye(N)[peaks[camera]]

    head = fit([_write(tmp_path / "fixed.maps", at_a_fixed_patch, seed=1)], OPTIONS)
    for camera, peak in zip(CAMERAS, peaks, strict=True):
        assert _figures(head, camera)["head"]["top1"] == _figures(head, camera)["prior"]["top1"] == 1.0
        assert int(np.argmax(head.position_bias[CAMERAS.index(camera)])) == peak


def test_the_fit_and_its_split_are_deterministic_from_the_seed(planted):
    root, head = planted
    again = fit([root], OPTIONS)
    assert occlusion_head.to_json(again) == occlusion_head.to_json(head)
    examples = read_examples([root], OPTIONS.inputs)
    held = {split(examples, 0.25, seed)[1].tobytes() for seed in range(4)}
    assert len(held) > 1  # another seed holds out other episodes
    fitting, held_rows = split(examples, 0.25, 0)
    assert not set(examples.episode[fitting]) & set(examples.episode[held_rows])  # whole episodes on one side


def test_the_head_file_round_trips_to_the_same_maps(planted, tmp_path):
    _, head = planted
    path = occlusion_head.save(head, tmp_path / "head.json")
    loaded = occlusion_head.load(path)
    assert occlusion_head.to_json(loaded) == occlusion_head.to_json(head)
    rng = np.random.default_rng(5)
    maps = {k: {c: rng.normal(size=(3, *GRID)).astype(np.float32) for c in CAMERAS} for k in head.inputs}
    for camera, predicted in head.predict(maps).items():
        # float64 weights survive JSON exactly: the same numbers, not merely close ones
        np.testing.assert_array_equal(loaded.predict(maps)[camera], predicted)
        assert predicted.shape == (3, *GRID) and predicted.dtype == np.float32
    assert occlusion_head.to_json(occlusion_head.load_ref(HeadRef.of(path))) == occlusion_head.to_json(head)


def test_predict_normalises_each_score_and_refuses_maps_of_another_model(planted):
    _, head = planted
    rng = np.random.default_rng(6)
    maps = {k: {c: rng.normal(size=GRID) for c in CAMERAS} for k in head.inputs}
    scaled = {k: {c: m * 1e3 for c, m in per_camera.items()} for k, per_camera in maps.items()}
    for camera in CAMERAS:  # the head reads each map divided by its largest |value|
        np.testing.assert_allclose(head.predict(scaled)[camera], head.predict(maps)[camera], rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError) as e:
        head.predict({"gradnorm": maps["gradnorm"]})
    assert_one_line(e.value, "lrp")
    with pytest.raises(ValueError) as e:
        head.predict({k: {c: rng.normal(size=(16, 16)) for c in CAMERAS} for k in head.inputs})
    assert_one_line(e.value, "(4, 4)", "(16, 16)")
    with pytest.raises(ValueError) as e:
        head.predict({k: {"base_0_rgb": m["base_0_rgb"]} for k, m in maps.items()})
    assert_one_line(e.value, "wrist_0_rgb")


def _corrupt(data: dict, how: str) -> str:
    if how == "truncated":
        return json.dumps(data)[:200]
    data = json.loads(json.dumps(data))
    if how == "format":
        data["format"] = "openpi-cam monitor"
    elif how == "version":
        data["format_version"] = 99
    elif how == "shape":
        data["weights"]["w2"] = data["weights"]["w2"][:-1]
    elif how == "nan":
        data["weights"]["position_bias"][0][0] = float("nan")
    elif how == "inputs":
        data["inputs"] = ["occlusion"]
    elif how == "normalisation":
        data["normalisation"] = "z-score"
    return json.dumps(data)


@pytest.mark.parametrize(
    ("how", "named"),
    [
        ("truncated", "not a JSON occlusion head file"),
        ("format", "not an occlusion head file"),
        ("version", "format_version 99"),
        ("shape", "weights.w2"),
        ("nan", "weights.position_bias has non-finite values"),
        ("inputs", "inputs must be"),
        ("normalisation", "normalisation 'z-score'"),
    ],
)
def test_a_corrupt_head_file_is_refused_in_one_line(planted, tmp_path, how, named):
    _, head = planted
    path = tmp_path / "bad.json"
    path.write_text(_corrupt(occlusion_head.to_json(head), how))
    with pytest.raises(ValueError) as e:
        occlusion_head.load(path)
    assert_one_line(e.value, str(path), named)
    with pytest.raises(ValueError) as e:
        occlusion_head.load_ref(HeadRef.of(path))
    assert_one_line(e.value, str(path), named)


def test_a_head_file_changed_after_it_was_named_is_refused(planted, tmp_path):
    """A run records its head by the SHA-256 of the file: a file rewritten since may not stand in for it."""
    _, head = planted
    path = occlusion_head.save(head, tmp_path / "head.json")
    ref = HeadRef.of(path)
    occlusion_head.save(dataclasses.replace(head, b2=head.b2 + 1.0), path)
    with pytest.raises(ValueError) as e:
        occlusion_head.load_ref(ref)
    assert_one_line(e.value, str(path), "changed")
    with pytest.raises(ValueError) as e:
        HeadRef.of(tmp_path / "missing.json")
    assert_one_line(e.value, "missing.json")


def test_options_record_the_head_by_its_bytes_not_its_path(planted, tmp_path):
    _, head = planted
    first = HeadRef.of(occlusion_head.save(head, tmp_path / "a.json"))
    moved = HeadRef.of(occlusion_head.save(head, tmp_path / "b.json"))
    other = HeadRef.of(occlusion_head.save(dataclasses.replace(head, b2=2.0), tmp_path / "c.json"))
    options = ExplainOptions(maps=("gradnorm", OCCLUSION_HEAD), occlusion_head=first)
    recorded = options.to_json()
    assert ExplainOptions.from_json(recorded) == options
    assert dataclasses.replace(options, occlusion_head=moved).mismatch(recorded) == []
    assert dataclasses.replace(options, occlusion_head=other).mismatch(recorded) == [
        f"occlusion_head: {first.sha256!r} != {other.sha256!r}"
    ]
    # runs made before the kind existed recorded no head
    assert ExplainOptions().mismatch({k: v for k, v in ExplainOptions().to_json().items() if "head" not in k}) == []


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["--inputs", "occlusion"], "inputs must be"),
        (["--holdout", "0"], "--holdout"),
        (["--inputs", "ig"], "no ['ig'] maps"),
    ],
)
def test_head_fit_refuses_bad_input_in_one_line(planted, tmp_path, capsys, args, named):
    root, _ = planted
    with pytest.raises(SystemExit) as exited:
        cli.main(["head", "fit", str(root), "--out", str(tmp_path / "h.json"), *args])
    assert exited.value.code == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and named in err, err
    assert not (tmp_path / "h.json").exists()


def test_head_fit_refuses_datasets_of_two_policies(planted, tmp_path, capsys):
    root, _ = planted
    other = _write(tmp_path / "other.maps", _sign_by_camera, model={"config": "demo_reach_pi05"})
    with pytest.raises(SystemExit):
        cli.main(["head", "fit", str(root), str(other), "--out", str(tmp_path / "h.json"), "--inputs", "lrp"])
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "one head fits one policy" in err and "demo_reach_pi05" in err


def test_the_kind_is_asked_for_by_name_only():
    """No default computes or draws it (the maps bench chose occlusion itself), and no bundled model ships a head."""
    from openpi_cam.checkpoints.model_spec import BUNDLED_CONFIGS, ModelSpec
    from openpi_cam.cli.options import EVERY_KIND, ExplainFlags
    from openpi_cam.demo.run import DemoOptions
    from openpi_cam.vocabulary import COMPARED_KINDS, DEFAULT_KINDS, DEFAULT_MAP_KIND

    demos = (DemoOptions().map_kinds, DemoOptions(sim="metaworld").map_kinds)
    for kinds in (DEFAULT_KINDS, COMPARED_KINDS, ExplainFlags().maps, EVERY_KIND.maps, *demos):
        assert OCCLUSION_HEAD not in kinds
    assert DEFAULT_MAP_KIND != OCCLUSION_HEAD
    for name in BUNDLED_CONFIGS:
        assert not (ModelSpec.demo(name).assets() / occlusion_head.HEAD_FILE).exists(), name
