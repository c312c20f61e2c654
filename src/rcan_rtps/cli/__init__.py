"""The `rcan-rtps` command line, shaped like ros2cli. No public Python API: run the command."""

__all__: list[str] = []
