"""The `occlusion-head` kind on the bundled demo model, end to end: frames of a LeRobot-written demo dataset explained
with the gradient norm and occlusion, a head fitted to them by `openpi-cam head fit`, then that head applied when
explaining the dataset and when serving (the demo's websocket server and side channel). Every frame and step
carries the kind, equal to the head applied to the same call's stored gradient-norm maps; the run and the maps dataset
record the head, a maps dataset refuses to resume with another, and a head that does not fit the request is refused
in one line before a model loads."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from datasets_support import model_job
from paths import LEROBOT_DIR

from openpi_cam import cli
from openpi_cam.cam.run_format import load_run
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.cli.options import ExplainFlags
from openpi_cam.demo.run import DemoOptions, run_demo
from openpi_cam.maps import dataset as fmt
from openpi_cam.maps.explain import run_local
from openpi_cam.model import occlusion_head
from openpi_cam.vocabulary import OCCLUSION_HEAD, ExplainOptions, HeadRef

SOURCE = LEROBOT_DIR / "demo_reach_v30_image"
# The demo's own target, so that the head fitted on the dataset serves the demo as it is.
TARGET = "chunk"
KINDS = ("gradnorm", OCCLUSION_HEAD)


@pytest.fixture(scope="module")
def head_file(tmp_path_factory, demo_policy):
    """A head fitted by the command on every 5th frame of the dataset's 8 episodes (15 frames, 2 episodes held out),
    read from the gradient norm alone: small and quick, and what it ranks is beside the point here."""
    root = tmp_path_factory.mktemp("fit") / "fit.maps"
    options = ExplainOptions(target=TARGET, maps=("gradnorm", "occlusion"), check_patches=0)
    run_local(model_job(SOURCE, root, options, every=5), policy=demo_policy)
    path = root.parent / "head.json"
    cli.main(["head", "fit", str(root), "--out", str(path), "--inputs", "gradnorm", "--hidden", "4", "--steps", "300"])
    head = occlusion_head.load(path)
    assert head.inputs == ("gradnorm",) and head.target == TARGET and head.model["config"] == "demo_reach"
    assert head.fit["examples"]["held_out"] > 0
    return path


def _assert_head_of_stored_inputs(head: occlusion_head.OcclusionHead, inputs: dict, maps: dict) -> None:
    """The kind's maps are the head applied to the stored input maps: the same float32 numbers."""
    predicted = head.predict({"gradnorm": inputs})
    assert set(maps) == set(predicted) == set(head.cameras)
    for camera, m in maps.items():
        np.testing.assert_array_equal(m, predicted[camera])
        assert np.ptp(m) > 0  # a map, not a constant


def test_explaining_a_dataset_with_the_kind(head_file, demo_policy, tmp_path):
    head = occlusion_head.load(head_file)
    options = ExplainFlags(target=TARGET, maps=KINDS, head=head_file, check_patches=2).options(model=ModelSpec())
    job = model_job(SOURCE, tmp_path / "head.maps", options, every=5, episodes=(0, 1))
    run_local(job, policy=demo_policy)
    maps = fmt.open_maps_dataset(job.out)
    assert maps.kinds == list(KINDS) and maps.info.options["occlusion_head"] == HeadRef.of(head_file).sha256
    rows = list(maps.rows())
    assert rows
    for row in rows:
        grid = maps.grid(head.cameras[0])
        inputs = {c: np.asarray(row[fmt.map_column("gradnorm", c)], np.float32).reshape(grid) for c in head.cameras}
        stored = {c: np.asarray(row[fmt.map_column(OCCLUSION_HEAD, c)], np.float32).reshape(grid) for c in head.cameras}
        _assert_head_of_stored_inputs(head, inputs, stored)
        assert json.loads(row["details"])["occlusion_head"]["inputs"] == ["gradnorm"]
        assert row[fmt.check_column(OCCLUSION_HEAD, "base_0_rgb")] is not None  # its top patch is spot-checked
    # Adding to it with another head is refused, naming what differs.
    other = occlusion_head.save(dataclasses.replace(head, b2=head.b2 + 1.0), tmp_path / "other.json")
    resumed = dataclasses.replace(job, options=dataclasses.replace(options, occlusion_head=HeadRef.of(other)))
    with pytest.raises(ValueError, match="occlusion_head"):
        run_local(resumed, policy=demo_policy)


def test_serving_with_the_kind(head_file, tmp_path):
    """The head served through the demo's websocket server and side channel: each step file holds the kind, computed
    from the gradient norm of the same call, which the step also stores."""
    result = run_demo(
        DemoOptions(
            out=tmp_path,
            num_episodes=1,
            max_calls=2,
            seed=20001,
            maps=KINDS,
            head=head_file,
            faithfulness=False,
            render=False,
        )
    )
    run = load_run(result.run_dir)
    head = occlusion_head.load(head_file)
    assert run.steps and run.run_info["options"]["occlusion_head"] == HeadRef.of(head_file).sha256
    for step in run.steps:
        assert step.map_kinds == KINDS and step.meta.target == TARGET
        _assert_head_of_stored_inputs(head, step.maps_of("gradnorm"), step.maps_of(OCCLUSION_HEAD))
        assert OCCLUSION_HEAD in step.meta.check.cameras["base_0_rgb"].top_patch


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["--maps", OCCLUSION_HEAD], "needs a head file"),  # the bundled model ships none
        (["--maps", OCCLUSION_HEAD, "--head", "HEAD", "--target", "action-token"], "fitted on chunk maps"),
        (["--maps", OCCLUSION_HEAD, "--head", "HEAD", "--config", "demo_reach_pi05"], "fitted for config demo_reach"),
    ],
)
def test_a_head_that_does_not_fit_is_refused_in_one_line(head_file, tmp_path, capsys, args, named):
    args = [str(head_file) if a == "HEAD" else a for a in args]
    with pytest.raises(SystemExit) as exited:
        cli.main(["explain-dataset", str(SOURCE), "--out", str(tmp_path / "x.maps"), "--no-progress", *args])
    assert exited.value.code == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and named in err, err
    assert not (tmp_path / "x.maps").exists()


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["--maps", "gradnorm", "--head", "HEAD"], f"given but {OCCLUSION_HEAD} is not among the maps"),
        (["--maps", OCCLUSION_HEAD, "--head", "NO_SUCH_HEAD"], "cannot read the occlusion head file"),
    ],
)
def test_a_head_flag_that_cannot_serve_is_refused_as_the_command_line_is_parsed(head_file, capsys, args, named):
    args = [str(head_file) if a == "HEAD" else a for a in args]
    with pytest.raises(SystemExit) as exited:
        cli.main(["explain-dataset", str(SOURCE), "--no-progress", *args])
    assert exited.value.code == 2
    assert named in " ".join(capsys.readouterr().err.split())  # tyro wraps the message in a box
