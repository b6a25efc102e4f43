"""LeRobot's formats, both directions, with pyarrow, PyAV and safetensors (no torch): datasets read (v2.x and v3.0)
and written (v3.0: rollouts and served connections recorded as `lerobot-eval` records them), pi0 / pi0.5 policy
folders served by their own processor files, and OpenPI checkpoints exported as such folders."""
