"""skinmap: software for a skin-like conformal shape sensor.

The public entry points of the numerical core are re-exported here::

    from skinmap import reconstruct, decouple
"""
from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["__version__", "reconstruct", "decouple"]


def __getattr__(name: str):
    # Lazy, so that `import skinmap.protocol` does not pay for scipy/clarabel.
    if name in ("reconstruct", "decouple"):
        from skinmap import reconstruction

        return getattr(reconstruction, name)
    raise AttributeError(f"module 'skinmap' has no attribute {name!r}")
