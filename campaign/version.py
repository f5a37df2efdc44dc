"""The package version, the one place it is written (pyproject.toml reads it; stores record it as
``package_version``). How it changes: docs/DEVELOPMENT.md, "Versions and the changelog"."""

__version__ = "0.3.0"
