"""Fixtures of the serving tests: the policies and a running server over the bundled demo model."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from openpi_cam.policies.policy import create_policy
from openpi_cam.serving.server import (
    start_server_in_thread,
)


@pytest.fixture(scope="module")
def policy(tiny_droid_policy):
    """For the error paths and the server's own behaviour, where which actions come back does not matter."""
    return tiny_droid_policy


@pytest.fixture(scope="module")
def metadata(demo_policy) -> dict:
    # Extra entries check that arrays and scalars in the metadata survive the trip to the real client.
    return {
        **demo_policy.metadata,
        "probe_array": np.arange(6, dtype=">i2").reshape(2, 3),
        "probe_scalar": np.float32(0.5),
    }


@pytest.fixture(scope="module")
def env_policies(tiny_policy_files, tmp_path_factory) -> dict[str, Any]:
    """LIBERO and ALOHA policies over the tiny DROID checkpoint's params.

    Their configs read norm stats under other asset ids and with other dimensions, so a scratch checkpoint links the
    same params and carries seeded stats of the right sizes.
    """
    from openpi_cam.normalize import compute_norm_stats, save_norm_stats
    from openpi_cam.policies.config import get_config

    policies = {}
    rng = np.random.default_rng(0)
    for env, name, state_dim, action_dim in [("libero", "pi0_fast_libero", 8, 7), ("aloha", "pi0_fast_aloha", 14, 14)]:
        checkpoint = tmp_path_factory.mktemp(f"{env}_checkpoint")
        (checkpoint / "params").symlink_to(tiny_policy_files.checkpoint / "params", target_is_directory=True)
        stats = {
            "state": compute_norm_stats(rng.normal(size=(64, state_dim))),
            "actions": compute_norm_stats(rng.normal(size=(64, action_dim))),
        }
        save_norm_stats(checkpoint / "assets" / get_config(name).asset_id, stats)
        policies[env] = create_policy(name, checkpoint, **tiny_policy_files.create_kwargs())
    return policies


@pytest.fixture(scope="module")
def server(demo_policy, metadata):
    running = start_server_in_thread(demo_policy, metadata=metadata, close_policy_on_stop=False)
    yield running
    running.stop()
