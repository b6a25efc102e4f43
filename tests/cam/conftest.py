"""Fixtures of the cam tests (side channel, run format, offline explanation)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def demo_policy():
    """The bundled demo policy (float32, 64 px, two cameras, 4 x 4 grid); its compiled programs are shared by every
    policy of the same config in this process."""
    from openpi_cam.policies import demo_reach

    return demo_reach.create_demo_policy()
