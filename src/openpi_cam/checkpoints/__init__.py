"""Which model a command loads: `ModelSpec`, the flags every command takes, resolved once into its source (the
bundled demo model, an OpenPI checkpoint with a named config, or a LeRobot policy folder) and recorded by every run
and maps dataset."""
