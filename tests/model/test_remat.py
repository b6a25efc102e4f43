"""The explanation's backward layout: layer activations kept where the device has room, recomputed (remat) where it
has not or does not say, and the maps the same either way.

The CPU reports no device memory, so a device's report is stood in for by replacing `remat.free_device_bytes` (the
one function that asks the device); everything else runs for real: XLA compiles the remat-free program, its memory
analysis decides, and the explanation runs with the chosen layout. Maps are compared within the tolerances of the
golden tests (recomputing a layer repeats the same float32 operations; measured differences are at most ~1e-6 of
the largest value).
"""

from __future__ import annotations

import dataclasses
import logging

import jax
import numpy as np
import pytest
from test_pi0 import CAMERAS as PI0_CAMERAS
from test_pi0 import load_case, load_model
from test_pi0_fast_maps import CAMERAS, GRAD_REL, LOGITS_REL, assert_close_rel, case

from openpi_cam.model import pi0_fast_maps, pi0_maps, remat
from openpi_cam.model.pi0 import Pi0
from openpi_cam.model.pi0_fast import Pi0FAST


def with_remat(model):
    """The same parameters under a config whose stacks recompute their layers, as full-size checkpoints do."""
    cfg = model.config
    changes = {
        f.name: dataclasses.replace(getattr(cfg, f.name), remat=True)
        for f in dataclasses.fields(cfg)
        if f.name in ("gemma", "expert")
    }
    return type(model)(dataclasses.replace(cfg, **changes), model.params)


@pytest.fixture
def device_reports(monkeypatch):
    """Makes the device report `free` bytes (None: no report, as the CPU) from now on; returns the decisions taken,
    forgetting earlier ones unless `keep`."""

    def report(free, keep=False):
        monkeypatch.setattr(remat, "free_device_bytes", lambda params: free)
        if not keep:
            remat._fits.clear()
        return remat._fits

    yield report
    remat._fits.clear()


def test_the_device_report_is_read_from_the_params_device(tiny_fast_model: Pi0FAST):
    """The CPU reports nothing (else CI's CPU would decide from a figure that does not bound host memory); an
    accelerator reports its free bytes."""
    free = remat.free_device_bytes(tiny_fast_model.params)
    if jax.default_backend() == "cpu":
        assert free is None
    else:
        assert isinstance(free, int) and free > 0


def test_without_remat_turns_off_every_stack_and_leaves_other_fields():
    pi0 = with_remat(load_model("pi0"))
    lean = remat.without_remat(pi0.config)
    assert pi0.config.gemma.remat and pi0.config.expert.remat
    assert not lean.gemma.remat and not lean.expert.remat
    assert dataclasses.replace(lean, gemma=pi0.config.gemma, expert=pi0.config.expert) == pi0.config
    assert remat.without_remat(lean) is lean


@pytest.mark.slow
@pytest.mark.parametrize("steps", [[3], [1, 2]], ids=["one token", "two tokens"])
def test_pi0_fast_drops_remat_only_where_the_program_fits(tiny_fast_model: Pi0FAST, device_reports, caplog, steps):
    """Room on the device: the remat-free program runs, compiled once (the memory analysis compiles the program that
    then runs); no room, or no report: remat is kept. The maps and scores are the same in every case."""
    data, obs = case("case_a")
    tokens = data["output_tokens"]
    model = with_remat(tiny_fast_model)
    reference = pi0_fast_maps.maps_for_steps(tiny_fast_model, obs, tokens, steps)

    def explain(free):
        decisions = device_reports(free)
        jax.clear_caches()  # every program of this call compiles here, so the count below is exact
        caplog.clear()
        with jax.log_compiles(), caplog.at_level(logging.WARNING, logger="jax"):
            res = pi0_fast_maps.maps_for_steps(model, obs, tokens, steps)
        finished = "Finished XLA compilation of jit(_token_gradient_maps)"
        compiled = sum(finished in r.getMessage() for r in caplog.records)
        assert_close_rel(res.score, reference.score, LOGITS_REL, "score")
        for c in CAMERAS:
            for kind in ("gradcam", "gradnorm"):
                assert_close_rel(res.by_kind[kind][c], reference.by_kind[kind][c], GRAD_REL, f"{kind} {c}")
        return dict(decisions), compiled

    assert explain(None) == ({}, 1)  # no report: nothing analysed, the configured layout
    decisions, compiled = explain(10**12)
    assert list(decisions.values()) == [True] and compiled == 1  # the analysed program is the one that ran
    ((program, lean_cfg, *_),) = decisions
    assert program is pi0_fast_maps._token_gradient_maps
    assert lean_cfg == pi0_fast_maps.backward_config(remat.without_remat(model.config), len(steps))
    assert not lean_cfg.gemma.remat
    decisions, compiled = explain(1)
    assert list(decisions.values()) == [False] and compiled == 2  # the analysed one, then the remat program


@pytest.mark.slow
def test_pi0_fast_chunk_target_follows_the_same_rule(tiny_fast_model: Pi0FAST, device_reports):
    data, obs = case("case_a")
    tokens = data["output_tokens"]
    chunk = [2, 3, 4, 5]
    reference = pi0_fast_maps.maps_for_chunk(tiny_fast_model, obs, tokens, chunk)
    model = with_remat(tiny_fast_model)
    for free, expected in ((10**12, True), (1, False)):
        decisions = device_reports(free)
        res = pi0_fast_maps.maps_for_chunk(model, obs, tokens, chunk)
        assert [k[0] for k in decisions] == [pi0_fast_maps._chunk_gradient_maps]
        assert list(decisions.values()) == [expected]
        assert_close_rel(res.score, reference.score, LOGITS_REL, "score")
        for c, m in res.by_kind["gradcam"].items():
            assert_close_rel(m, reference.by_kind["gradcam"][c], GRAD_REL, f"gradcam {c}")


@pytest.mark.slow
@pytest.mark.parametrize("family", ["pi0", "pi05"])
def test_pi0_flow_explanations_follow_the_same_rule(device_reports, family):
    """pi0 / pi0.5: both stacks (PaliGemma and the action expert) drop remat together where the program fits."""
    base: Pi0 = load_model(family)
    model = with_remat(base)
    d, obs = load_case(family, "case_a")
    targets = [(0, 6), pi0_maps.CHUNK]
    reference = pi0_maps.maps_for_actions(base, obs, d["noise"], targets)
    for free, expected in ((10**12, True), (1, False)):
        decisions = device_reports(free)
        res = pi0_maps.maps_for_actions(model, obs, d["noise"], targets)
        ((key, fits),) = decisions.items()
        assert fits is expected and not key[1].gemma.remat and not key[1].expert.remat
        np.testing.assert_array_equal(res.actions, reference.actions)
        for c in PI0_CAMERAS:
            for kind in ("gradcam", "gradnorm"):
                assert_close_rel(res.by_kind[kind][c], reference.by_kind[kind][c], GRAD_REL, f"{kind} {c}")


def test_the_decision_is_taken_once_per_program_signature(tiny_fast_model: Pi0FAST, device_reports):
    """A later explanation of the same shapes reuses the decision (no second analysis), whatever the device says
    then: the layout of a compiled program does not flip between requests."""
    data, obs = case("case_a")
    model = with_remat(tiny_fast_model)
    decisions = device_reports(10**12)
    pi0_fast_maps.maps_for_steps(model, obs, data["output_tokens"], [3])
    device_reports(1, keep=True)
    pi0_fast_maps.maps_for_steps(model, obs, data["output_tokens"], [4])
    assert list(decisions.values()) == [True]
