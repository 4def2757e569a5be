"""Shape reconstruction: gauge strains → the sheet's 3D surface (see docs/reconstruction.md).

    from skinmap import reconstruct
    surf = reconstruct(eps_upper, eps_lower, pitch=12.0, h_upper=0.2, h_lower=0.2)
    surf.nodes, surf.normals, surf.node_sigma        # (N, M, 3), (N, M, 3), (N, M)
    pos, nrm = surf.locate(uv)                       # any material points (K, 2) mm
    cloud = surf.points(per_pitch=20)

Per-geometry precomputation (operators and their factorisations) lives in a
:class:`Reconstructor`; :func:`reconstruct` keeps a small cache of them keyed by the geometry.

Modules, in the order a frame meets them: :mod:`.decouple` (a gauge pair → stretch and turning),
:mod:`.robust` (the gauge screen), :mod:`.graphfit` and :mod:`.graphsheet` (the height graph),
:mod:`.engine` with :mod:`.grid`, :mod:`.kernels` and :mod:`.linalg` (the general model),
:mod:`.forward` (the gauges' exact forward model), :mod:`.membrane`, :mod:`.airy` and
:mod:`.productnoise` (what the stretch pattern and the noise say of the twist), :mod:`.stretchtwist`
and :mod:`.twistfamily` (an answer held to the stretch pattern's twist, along its twist family),
:mod:`.positionfit` (the opt-in elastic prior), :mod:`.uncertainty` and :mod:`.leaveout` (σ),
:mod:`.surface` (the answer); :mod:`.reconstructor` runs them.
"""
from __future__ import annotations

from .decouple import decouple
from .reconstructor import (
    DEFAULT_GAIN_SD,
    DEFAULT_STRAIN_SIGMA,
    ELASTIC_PRIOR_MAX_CELLS,
    GRAPH_AGREE_SIGMAS,
    GRAPH_FIT_MAX_CELLS,
    Reconstructor,
    default_subdivision,
    nodes_in_sensor_frame,
    reconstruct,
    to_sensor_frame,
)
from .surface import Diagnostics, FrameState, Surface

__all__ = ["reconstruct", "decouple", "Reconstructor", "Surface", "FrameState", "Diagnostics", "DEFAULT_STRAIN_SIGMA",
           "DEFAULT_GAIN_SD",
           "GRAPH_FIT_MAX_CELLS", "GRAPH_AGREE_SIGMAS", "ELASTIC_PRIOR_MAX_CELLS", "default_subdivision",
           "to_sensor_frame", "nodes_in_sensor_frame"]
