"""Private implementation layer; the public API is re-exported by ``tlsjax/__init__.py``."""
