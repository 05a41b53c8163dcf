"""The installed version of tlsjax (package metadata), for the package and for the provenance
that reports write."""

try:
    from importlib.metadata import version as _version

    __version__ = _version("tlsjax")
except Exception:  # pragma: no cover - running from a source tree without metadata
    __version__ = "0.1.0"
