"""openpi-cam: an OpenPI-compatible pi0-FAST policy server with a Grad-CAM side channel."""

__version__ = "0.1.0"
