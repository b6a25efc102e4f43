"""openpi-cam: an OpenPI-compatible policy server for pi0-FAST, pi0 and pi0.5 with a side channel that logs maps
explaining each served action (Grad-CAM, gradient norm, integrated gradients, occlusion)."""

__version__ = "0.1.0"
