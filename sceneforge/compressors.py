"""The store's compressors' native extensions, loaded before any library that could take
over their symbols.

numcodecs' Blosc and zstd extensions carry their own zstd but export its symbols, and a
library loaded into the global namespace first takes them over: Mesa's EGL driver brings in
the system's libzstd, after which the same arrays compress to other (valid) bytes. A worker
that rendered before it first wrote made other shard files than a one-worker run (the arrays
decoded the same). So the raster renderer calls :func:`load_compressors` before it loads
pyrender and EGL. A module of its own, below both, so that the renderer need not import the
store (and the store not the renderer).
"""


def load_compressors() -> None:
    """Load numcodecs' Blosc and zstd extensions now (a no-op once they are loaded)."""
    import numcodecs.blosc  # noqa: F401
    import numcodecs.zstd  # noqa: F401
