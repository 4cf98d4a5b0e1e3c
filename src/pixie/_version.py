"""The package version (one place; read by reference-set files)."""

__version__ = "0.1.0"
