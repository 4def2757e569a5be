"""A PNG picture of the logged surface (`skinmap inspect --png`): the snapshot nearest a time,
drawn with matplotlib."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from skinmap.daemon.foxglove_log import decode_protobuf
from skinmap.daemon.mcapread import LoggedMessage, iter_messages_file_order
from skinmap.wire import messages as wire

__all__ = ["SurfaceSnapshot", "find_surface", "render_surface_png"]


@dataclass(frozen=True)
class SurfaceSnapshot:
    t_ns: int
    t_rel_s: float  # seconds after the first message of the file
    seq: int | None
    nodes: np.ndarray | None  # (N, M, 3) mm
    points: np.ndarray | None  # (P, 3) mm
    sigma: np.ndarray | None = None  # (N, M) mm, node 1-s.d. uncertainty
    elements: wire.ElementsMessage | None = None  # the elements logged nearest that time


def find_surface(path: str | os.PathLike[str], t_s: float | None = None) -> SurfaceSnapshot:
    """The logged surface nearest `t_s` seconds after the file's first message (the last one
    when `t_s` is None): nodes from `/surface/nodes`, points from `/surface` at that time."""
    if t_s is not None and not math.isfinite(t_s):
        raise ValueError(f"t_s must be a finite number of seconds, got {t_s!r}")
    first_ns: int | None = None
    best: dict[str, LoggedMessage] = {}
    best_err: dict[str, float] = {}
    for m in iter_messages_file_order(path):
        if first_ns is None:
            first_ns = m.log_time_ns
        if m.topic not in ("/surface/nodes", "/surface", "/elements"):
            continue
        err = 0.0 if t_s is None else abs((m.log_time_ns - first_ns) * 1e-9 - t_s)
        if t_s is None or err <= best_err.get(m.topic, math.inf):
            best[m.topic], best_err[m.topic] = m, err
    elements_msg = best.pop("/elements", None)
    key = "/surface/nodes" if "/surface/nodes" in best else "/surface"
    if key not in best or first_ns is None:
        raise ValueError(f"{os.fspath(path)}: no /surface or /surface/nodes messages")
    chosen = best[key]
    nodes = seq = points = sigma = None
    if key == "/surface/nodes":
        surface = wire.decode_surface(chosen.data)
        seq, nodes = surface.seq, surface.nodes * 1e3
        points = surface.cloud.astype(np.float64) * 1e3 if len(surface.cloud) else None
        sigma = surface.uncertainty * 1e3
    else:
        cloud = decode_protobuf(chosen.schema_name, chosen.data)
        raw = np.frombuffer(cloud.data, dtype="<f4")
        points = raw[: len(raw) // 3 * 3].reshape(-1, 3).astype(np.float64) * 1e3
    elements = None
    if elements_msg is not None:
        try:
            elements = wire.decode_elements(elements_msg.data)
        except wire.MessageError:
            elements = None  # drawn without elements; inspect names unusable records
    return SurfaceSnapshot(chosen.log_time_ns, (chosen.log_time_ns - first_ns) * 1e-9, seq,
                           nodes, points, sigma, elements)


def render_surface_png(path: str | os.PathLike[str], t_s: float | None,
                       out_png: str | os.PathLike[str]) -> SurfaceSnapshot:
    """Draw the logged surface nearest `t_s` (seconds after the first message; None = last)
    in 3D to `out_png`. Returns the snapshot drawn."""
    snap = find_surface(path, t_s)
    # Figure + Agg canvas directly: no global backend switch, works without a display.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 5.5), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    every = np.concatenate([a.reshape(-1, 3) for a in (snap.nodes, snap.points)
                            if a is not None])
    if snap.nodes is not None:
        x, y, z = (snap.nodes[..., k] for k in range(3))
        if snap.sigma is not None and min(snap.nodes.shape[:2]) >= 2:
            # Faces coloured by node σ (µm), with a colorbar: where the shape is less certain.
            from matplotlib import cm, colors

            sig_um = snap.sigma * 1e3
            norm = colors.Normalize(vmin=0.0, vmax=max(float(np.nanmax(sig_um)), 1e-3))
            ax.plot_surface(x, y, z, facecolors=cm.viridis(norm(sig_um)), edgecolor="k",
                            linewidth=0.3, alpha=0.85, shade=False)
            mappable = cm.ScalarMappable(norm=norm, cmap="viridis")
            fig.colorbar(mappable, ax=ax, shrink=0.6, pad=0.1, label="node σ, 1 s.d. (µm)")
        elif min(snap.nodes.shape[:2]) >= 2:
            ax.plot_surface(x, y, z, cmap="viridis", edgecolor="k", linewidth=0.3, alpha=0.85)
        else:
            ax.plot(x.ravel(), y.ravel(), z.ravel(), "o-")
    if snap.points is not None:
        p = snap.points[:: max(1, len(snap.points) // 5000)]
        ax.scatter(p[:, 0], p[:, 1], p[:, 2], s=1.5, c="tab:red", alpha=0.3)
    el = snap.elements
    if el is not None and el.count:
        pos, nrm = el.positions * 1e3, el.normals
        ok = np.isfinite(pos).all(axis=1) & np.isfinite(nrm).all(axis=1)
        valid = ok & el.valid
        span = float(np.ptp(every, axis=0).max()) if len(every) else 1.0
        arrow = 0.08 * max(span, 1.0)
        for mask, colour, label in ((valid, "tab:green", "element, VALID"),
                                    (ok & ~el.valid, "tab:orange", "element, not VALID")):
            if mask.any():
                ax.quiver(pos[mask, 0], pos[mask, 1], pos[mask, 2], nrm[mask, 0], nrm[mask, 1],
                          nrm[mask, 2], length=arrow, color=colour, linewidth=0.8, label=label)
                ax.scatter(pos[mask, 0], pos[mask, 1], pos[mask, 2], s=6, c=colour)
        if ok.any():
            every = np.concatenate([every, pos[ok]])
            ax.legend(loc="upper left", fontsize=7)
    lo, hi = every.min(axis=0), every.max(axis=0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-3)
    for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
        setter(c - half, c + half)  # equal scale so curvature is not distorted
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    seq = "" if snap.seq is None else f", seq {snap.seq}"
    if snap.sigma is not None and np.isfinite(snap.sigma).any():
        seq += f", node σ {np.nanmin(snap.sigma) * 1e3:.1f}..{np.nanmax(snap.sigma) * 1e3:.1f} µm"
    if snap.elements is not None:
        seq += f", {int(snap.elements.valid.sum())}/{snap.elements.count} elements VALID"
    ax.set_title(f"{os.path.basename(os.fspath(path))}\nt+{snap.t_rel_s:.3f} s{seq}",
                 fontsize=9)
    fig.savefig(os.fspath(out_png), format="png")
    return snap
