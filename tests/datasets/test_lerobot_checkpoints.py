"""A LeRobot policy folder explains a LeRobot dataset recorded with its own features, with no --config and no --keys:
the bundled pi0.5 exported as a LeRobot folder (`demo_pi05_lerobot`) against the JAX original on the LeRobot-written
demo dataset, and a dataset whose features do not fit the policy refused in one line naming the feature."""

from __future__ import annotations

import numpy as np
import pytest
from datasets_support import pointing
from paths import LEROBOT_DIR
from shared_copies import edit_json, writable_copy

from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.cli import explain_dataset
from openpi_cam.cli.options import ExplainFlags
from openpi_cam.maps import dataset as fmt

SOURCE = LEROBOT_DIR / "demo_reach_v30_image"  # lossless frames: the two models see the same pixels
FLAGS = ExplainFlags(maps=("gradnorm",), check_patches=0)
BOX = ("observation.target_box=target_box",)


@pytest.fixture(scope="module")
def explained(demo_pi05_lerobot, tmp_path_factory):
    """The demo dataset explained by the LeRobot folder (no config, no keys) and by the JAX original."""
    out = {}
    for name, model in (("lerobot", ModelSpec(demo_pi05_lerobot)), ("jax", ModelSpec(config="demo_reach_pi05"))):
        root = tmp_path_factory.mktemp(name) / "maps"
        code = explain_dataset.main(SOURCE, model=model, out=root, explanation=FLAGS, extra=BOX, progress=False)
        assert code == 0
        out[name] = fmt.open_maps_dataset(root)
    return out


def test_a_lerobot_folder_reads_the_dataset_by_its_own_feature_names(explained, demo_pi05_lerobot):
    info = explained["lerobot"].info
    assert info.model["config"] is None and info.model["checkpoint_dir"] == str(demo_pi05_lerobot.resolve())
    assert info.keys == {f: f for f in ("observation.images.base", "observation.images.wrist", "observation.state")}
    assert info.family == "pi05" and info.target == "chunk" and info.model["dtype"] == "float32"
    assert info.camera_sources["observation.images.base"] == "observation.images.base"


def test_its_maps_point_at_the_named_block_as_the_jax_originals_do(explained):
    """The exported folder is the same model: at the demo's own resolution (no resize) its maps equal the JAX
    original's up to float32 rounding, so the pointing figures agree to a frame (1 of 55 is 2 points)."""
    folder, original = explained["lerobot"], explained["jax"]
    (hit, chance), (jax_hit, jax_chance) = pointing(folder, folder.cameras[0]), pointing(original, original.cameras[0])
    assert chance == jax_chance and hit >= 3 * chance, (hit, chance)
    assert abs(hit - jax_hit) <= 0.02, (hit, jax_hit)
    ours, theirs = (
        explained["lerobot"].maps("gradnorm", "observation.images.base"),
        explained["jax"].maps("gradnorm", "base_0_rgb"),
    )
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-4 * float(np.abs(theirs).max()))


def test_a_dataset_that_does_not_fit_the_policy_is_refused_naming_the_feature(demo_pi05_lerobot, tmp_path, capsys):
    wrong = tmp_path / "wrong"
    writable_copy(SOURCE, wrong)

    def rename_wrist(info: dict) -> None:
        info["features"]["observation.images.top"] = info["features"].pop("observation.images.wrist")

    edit_json(wrong / "meta" / "info.json", rename_wrist)
    model = ModelSpec(demo_pi05_lerobot)
    assert explain_dataset.main(wrong, model=model, out=tmp_path / "o", explanation=FLAGS, progress=False) == 1
    line = capsys.readouterr().err.strip()
    assert "\n" not in line and "'observation.images.wrist'" in line and "is not in the dataset" in line


def test_what_a_ray_driver_plans_with_is_what_the_loaded_policy_says(demo_pi05_lerobot):
    """`ModelSpec.facts` reads family, patch grid and cameras without weights (a Ray driver's info.json); every actor
    checks the info its loaded model gives against it, so they must agree for every format."""
    for model in (ModelSpec(demo_pi05_lerobot), ModelSpec(), ModelSpec(config="demo_reach_pi05")):
        policy, facts = model.create(), model.facts()
        assert facts.family == policy.model.family, model
        assert facts.grid == policy.model.config.siglip.grid, model
        assert facts.camera_sources == dict(policy.camera_sources), model


def test_views_of_a_policy_with_a_blank_camera(explained):
    """A LeRobot folder's `empty_cameras` are masked: no frame of theirs has a map, and the views still hold."""
    from openpi_cam.maps.views import compute_views

    summary = compute_views(explained["lerobot"], "gradnorm").summary()
    cameras = summary["cameras"]
    assert cameras["observation.images.empty_camera_0"]["prior_fit"]["frames"] == 0
    assert cameras["observation.images.empty_camera_0"]["hot_patches"] == []
    assert cameras["observation.images.base"]["prior_fit"]["frames"] == summary["frames"]


def test_render_draws_a_lerobot_folders_maps(explained, tmp_path):
    from openpi_cam.cli import render

    out = tmp_path / "render"
    assert render.main(explained["lerobot"].root, out=out, videos=False, progress=False) == 0
    assert "observation.images.base" in (out / "index.html").read_text()
