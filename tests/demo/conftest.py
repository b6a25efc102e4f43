"""Fixtures of the demo tests."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def demo_policy():
    """The bundled demo policy, built once (compiled programs are shared by every policy of its config anyway)."""
    from openpi_cam.policies import demo_reach

    return demo_reach.create_demo_policy()
