"""Elastic-sheet mechanics: the sensor film as a thin elastic sheet, solved to equilibrium.

The film is discretised on a regular grid of material points (spacing ≤ 1.5 mm by default)
covering the sheet in its flat, unstressed state.  Its energy is

- **membrane**: Saint Venant–Kirchhoff in plane stress, W = λ'/2 (tr E)² + μ E:E per unit
  reference area with the Green strain E = (FᵀF − I)/2, Y = E·t, λ' = Yν/(1−ν²),
  μ = Y/(2(1+ν)); bilinear quadrilaterals, 2×2 Gauss points;
- **bending**: the discrete quadratic Kirchhoff energy D/2 Σ h_u h_v [(x_uu + x_vv)² −
  2(1−ν)(x_uu·x_vv − x_uv²)] from central second differences of the node positions (exact for
  isometric bending; its spurious in-plane coupling is of relative order D/(Y L²) < 0.2 %);
- **contact** with rigid bodies (molds below, fingertips, domes and walls above) as stiff
  penalties on a gap function g(x) at every node, bilateral (laminated: g = 0) or unilateral
  (g ≥ 0); the reaction is along ∇g, normal to the body: frictionless;
- optional **tangential foundation** k_t/2 |xy − xy₀|² (partial stick on a mold: k_t → ∞ keeps
  every material point over its first-contact point, k_t = 0 is frictionless);
- optional **pressurised balloon wall** under the sheet: T·A − p·V with Laplace's p = 2T/R.

Equilibrium is the minimum of the total energy over the free degrees of freedom (Dirichlet
conditions remove the others), found by a damped Newton method: element Hessians of the membrane
are projected onto positive semi-definite matrices (material part BᵀDB plus the geometric part
with the stress's positive part), the bending matrix is constant, contact uses its Gauss–Newton
term, the balloon's Hessian is exact; the sparse system is factorised by SuperLU, a Levenberg
shift is raised whenever a step fails to descend, and an Armijo line search guards every step.
The gradient is exact, so the converged state is a true equilibrium of the discrete energy
whatever the Hessian approximations.

Units: mm, N, N/mm (membrane stiffness), N·mm (bending stiffness).  Everything here is a pure
function of its arguments; no I/O.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Protocol, Sequence, cast

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

__all__ = [
    "MechanicsError",
    "SheetMaterial",
    "SheetGrid",
    "GapField",
    "HeightField",
    "FunctionHeight",
    "FlatHeight",
    "SphereHeight",
    "CylinderHeight",
    "MoldContact",
    "SphereContact",
    "WallContact",
    "Balloon",
    "SheetProblem",
    "Solution",
    "solve",
    "membrane_green_strain",
]


class MechanicsError(RuntimeError):
    """The equilibrium solve failed (no convergence, or an inconsistent problem)."""


@dataclass(frozen=True)
class SheetMaterial:
    """Elastic constants of the film.

    Defaults from the sensor's paper: effective modulus 562 kPa, a film of about 1 mm in all,
    bending stiffness about 0.083 N·mm; Poisson's ratio of a silicone elastomer (0.45–0.5)."""

    youngs_modulus: float = 0.562  # N/mm² (= MPa)
    thickness: float = 1.0  # mm
    poisson: float = 0.48
    bending_stiffness: float = 0.083  # N·mm

    def __post_init__(self) -> None:
        for name in ("youngs_modulus", "thickness", "bending_stiffness"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"sheet material {name} must be a finite positive number, got {value!r}")
        if not (0.0 <= self.poisson <= 0.5):
            raise ValueError(f"sheet material poisson must be in [0, 0.5], got {self.poisson!r}")

    @property
    def membrane_stiffness(self) -> float:
        """Y = E·t (N/mm)."""
        return self.youngs_modulus * self.thickness

    def lame(self) -> tuple[float, float]:
        """Plane-stress Lamé constants (λ', μ) of the membrane (N/mm)."""
        y, nu = self.membrane_stiffness, self.poisson
        return y * nu / (1.0 - nu * nu), y / (2.0 * (1.0 + nu))


@dataclass(frozen=True)
class SheetGrid:
    """Regular grid of material points on [−half_u, half_u] × [−half_v, half_v] (mm), spacing at
    most ``spacing``.  Node (i, j) sits at (u_j, v_i); arrays are (nv, nu, ...) like the cells."""

    half_u: float
    half_v: float
    spacing: float = 1.5

    def __post_init__(self) -> None:
        for name in ("half_u", "half_v", "spacing"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"sheet grid {name} must be a finite positive number, got {value!r}")

    @classmethod
    def for_array(cls, n: int, m: int, pitch: float, spacing: float = 1.5,
                  margin: float | None = None) -> "SheetGrid":
        """The film of an N×M array: the cells plus ``margin`` (default half a pitch) all round."""
        margin = 0.5 * pitch if margin is None else margin
        return cls(0.5 * m * pitch + margin, 0.5 * n * pitch + margin, spacing)

    @property
    def nu(self) -> int:
        return int(math.ceil(2.0 * self.half_u / self.spacing - 1e-9)) + 1

    @property
    def nv(self) -> int:
        return int(math.ceil(2.0 * self.half_v / self.spacing - 1e-9)) + 1

    @property
    def u(self) -> np.ndarray:
        return np.linspace(-self.half_u, self.half_u, self.nu)

    @property
    def v(self) -> np.ndarray:
        return np.linspace(-self.half_v, self.half_v, self.nv)

    @property
    def hu(self) -> float:
        return 2.0 * self.half_u / (self.nu - 1)

    @property
    def hv(self) -> float:
        return 2.0 * self.half_v / (self.nv - 1)

    def uv(self) -> np.ndarray:
        """Material coordinates of the nodes, (nv, nu, 2)."""
        uu, vv = np.meshgrid(self.u, self.v)
        return np.stack([uu, vv], axis=-1)

    def flat(self) -> np.ndarray:
        """Node positions of the flat, unstressed sheet, (nv, nu, 3)."""
        uv = self.uv()
        return np.concatenate([uv, np.zeros(uv.shape[:-1] + (1,))], axis=-1)


# --------------------------------------------------------------------------- rigid bodies


class HeightField(Protocol):
    """A surface z = f(x, y, t) with its gradient and Hessian (mm)."""

    def __call__(self, xy: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """f (K,), ∇f (K, 2), ∇²f (K, 2, 2) at points xy (K, 2)."""
        ...


class FlatHeight:
    """z = 0."""

    def __call__(self, xy: np.ndarray, t: float = 0.0):
        k = xy.shape[0]
        return np.zeros(k), np.zeros((k, 2)), np.zeros((k, 2, 2))

    def __repr__(self) -> str:
        return "FlatHeight()"


class SphereHeight:
    """The cap of a sphere of radius |R| touching z = 0 at the origin: convex (R > 0, centre at
    z = −R) or concave (R < 0, a bowl).  Beyond r = 0.999|R| the surface continues as its tangent
    cone, so points far off never see an undefined height."""

    def __init__(self, radius: float):
        if not math.isfinite(radius) or radius == 0:
            raise ValueError(f"sphere radius must be finite and non-zero, got {radius!r}")
        self.radius = float(radius)

    def __call__(self, xy: np.ndarray, t: float = 0.0):
        r_abs, s = abs(self.radius), math.copysign(1.0, self.radius)
        r2 = np.minimum(np.sum(xy * xy, axis=-1), (0.999 * r_abs) ** 2)
        q = np.sqrt(r_abs * r_abs - r2)
        f = s * (q - r_abs)
        grad = -s * xy / q[:, None]
        hess = -s * (np.eye(2) / q[:, None, None] + xy[:, :, None] * xy[:, None, :] / (q**3)[:, None, None])
        return f, grad, hess

    def __repr__(self) -> str:
        return f"SphereHeight(radius={self.radius!r})"


class CylinderHeight:
    """A circular cylinder of radius |R| touching z = 0 along its axis through the origin; the axis
    is turned ``axis_angle`` degrees from +v toward +u (as the kinematic ``Cylinder``)."""

    def __init__(self, radius: float, axis_angle: float = 0.0):
        if not math.isfinite(radius) or radius == 0:
            raise ValueError(f"cylinder radius must be finite and non-zero, got {radius!r}")
        self.radius = float(radius)
        self.axis_angle = float(axis_angle)
        th = math.radians(self.axis_angle)
        self._across = np.array([math.cos(th), -math.sin(th)])

    def __call__(self, xy: np.ndarray, t: float = 0.0):
        r_abs, s = abs(self.radius), math.copysign(1.0, self.radius)
        w = np.clip(xy @ self._across, -0.999 * r_abs, 0.999 * r_abs)
        q = np.sqrt(r_abs * r_abs - w * w)
        f = s * (q - r_abs)
        grad = (-s * w / q)[:, None] * self._across
        curv = -s * r_abs * r_abs / q**3
        hess = curv[:, None, None] * np.outer(self._across, self._across)
        return f, grad, hess

    def __repr__(self) -> str:
        return f"CylinderHeight(radius={self.radius!r}, axis_angle={self.axis_angle!r})"


class FunctionHeight:
    """Any height function: ``height_and_gradient(xy, t) -> (f, ∇f)`` (for example a kinematic
    graph shape's); the Hessian comes from central differences of the gradient (step 1e-4 mm,
    error ~1e-9 of the curvature for millimetre features)."""

    _STEP = 1e-4

    def __init__(self, height_and_gradient: Callable[[np.ndarray, float], tuple[np.ndarray, np.ndarray]],
                 label: str = "FunctionHeight"):
        self._fn = height_and_gradient
        self.label = label

    def __call__(self, xy: np.ndarray, t: float = 0.0):
        f, grad = self._fn(xy, t)
        d = self._STEP
        hess = np.empty(xy.shape[:-1] + (2, 2))
        for k in range(2):
            e = np.zeros(2)
            e[k] = d
            gp = self._fn(xy + e, t)[1]
            gm = self._fn(xy - e, t)[1]
            hess[:, :, k] = (gp - gm) / (2.0 * d)
        return np.asarray(f, float), np.asarray(grad, float), 0.5 * (hess + np.swapaxes(hess, 1, 2))

    def __repr__(self) -> str:
        return self.label


class GapField(Protocol):
    """A rigid body's signed gap at the sheet's nodes: g (K,), ∇g (K, 3); g ≥ 0 is admissible."""

    @property
    def bilateral(self) -> bool:
        """True: held at g = 0 (laminated); False: only kept at g ≥ 0."""
        ...

    def gap(self, x: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        ...

    def project(self, x: np.ndarray, t: float) -> np.ndarray:
        """The points (K, 3) moved to the nearest admissible place (a start for the solver)."""
        ...


@dataclass(frozen=True)
class MoldContact:
    """The sheet's mid-surface on a mold z = f(x, y) below it: g = z − f.  ``bilateral`` (default)
    holds the film on the mold everywhere (laminated); otherwise it may lift off."""

    height: HeightField
    bilateral: bool = True

    def gap(self, x: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        f, grad, _ = self.height(x[:, :2], t)
        dg = np.concatenate([-grad, np.ones((x.shape[0], 1))], axis=1)
        return x[:, 2] - f, dg

    def project(self, x: np.ndarray, t: float) -> np.ndarray:
        f, _, _ = self.height(x[:, :2], t)
        out = x.copy()
        out[:, 2] = f if self.bilateral else np.maximum(x[:, 2], f)
        return out


@dataclass(frozen=True)
class WallContact:
    """A rigid wall z = f(x, y) above the sheet (a relief pressed onto it): g = f − z ≥ 0."""

    height: HeightField
    bilateral: bool = False

    def gap(self, x: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        f, grad, _ = self.height(x[:, :2], t)
        dg = np.concatenate([grad, -np.ones((x.shape[0], 1))], axis=1)
        return f - x[:, 2], dg

    def project(self, x: np.ndarray, t: float) -> np.ndarray:
        f, _, _ = self.height(x[:, :2], t)
        out = x.copy()
        out[:, 2] = np.minimum(x[:, 2], f)
        return out


@dataclass(frozen=True)
class SphereContact:
    """A rigid sphere (fingertip, dome) the mid-surface stays outside of: g = |x − c(t)| − r,
    r being the body's radius plus half the film's thickness."""

    centre: Callable[[float], np.ndarray]
    radius: float
    bilateral: bool = False

    def gap(self, x: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        d = x - np.asarray(self.centre(t), float)
        dist = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        return dist - self.radius, d / dist[:, None]

    def project(self, x: np.ndarray, t: float) -> np.ndarray:
        c = np.asarray(self.centre(t), float)
        d = x - c
        dist = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        inside = dist < self.radius
        out = x.copy()
        # a point inside goes out along its ray from the centre (straight up from the centre itself)
        ray = np.where((dist > 1e-9)[:, None], d / dist[:, None], np.array([0.0, 0.0, -1.0]))
        out[inside] = c + self.radius * ray[inside]
        return out


@dataclass(frozen=True)
class Balloon:
    """A pressurised balloon wall under the sheet, moving with it (frictionless between them):
    energy T·A − p·V with membrane tension ``tension`` (N/mm) and Laplace's pressure
    p = 2T/R for a balloon of radius ``radius`` (mm) centred at ``centre``."""

    tension: float
    radius: float
    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def pressure(self) -> float:
        return 2.0 * self.tension / self.radius


# --------------------------------------------------------------------------- the problem


@dataclass
class SheetProblem:
    """Everything an equilibrium solve needs.  ``fixed`` (nv, nu, 3) bool marks the degrees of
    freedom held at ``x0``'s value (Dirichlet); ``active`` (nv−1, nu−1) bool the elements that are
    film (a mask for non-rectangular sheets); ``reference`` (nv, nu, 2) the xy points the
    tangential foundation pulls toward (default: the material coordinates)."""

    grid: SheetGrid
    material: SheetMaterial = field(default_factory=SheetMaterial)
    mold: HeightField | None = None  # the film laminated on it: z = f(x, y, t), sliding freely
    contacts: Sequence[GapField] = ()
    fixed: np.ndarray | None = None
    active: np.ndarray | None = None
    foundation: float = 0.0  # k_t, N/mm³
    reference: np.ndarray | None = None
    balloon: Balloon | None = None
    penalty: float | None = None  # contact stiffness per area, N/mm³ (default 100·Y/h²: about 0.1 µm of overlap under a fingertip)
    # the film's mean in-plane motions held at the start's: any of "x", "y" (translations) and
    # "turn" (rotation about the normal); for frictionless films no edge or pin holds
    hold_rigid: tuple[str, ...] = ()
    time: float = 0.0


@dataclass
class Solution:
    """Equilibrium node positions (nv, nu, 3) and how the solve went."""

    grid: SheetGrid
    positions: np.ndarray
    energy: float
    iterations: int
    residual: float  # largest free force component at the end (N)
    seconds: float
    # the last sparse factor and the free set it belongs to: a preconditioner for the next,
    # nearby solve of the same problem (a moving scene's next key frame)
    preconditioner: "_Factor | None" = field(default=None, repr=False, compare=False)
    free: np.ndarray | None = field(default=None, repr=False, compare=False)


# Bilinear element on [0, hu] × [0, hv]; local corners in the order (0,0), (0,1), (1,1), (1,0)
# as (dv, du) offsets, 2×2 Gauss points.
_CORNERS = np.array([[0, 0], [0, 1], [1, 1], [1, 0]])  # (dv, du)
_GAUSS = np.array([-1.0, 1.0]) / math.sqrt(3.0)


def _shape_functions(hu: float, hv: float) -> tuple[np.ndarray, np.ndarray, float]:
    """N (Q, 4), dN (Q, 4, 2) (d/du, d/dv) and the Gauss weight (hu·hv/4)."""
    xi_a = 2.0 * _CORNERS[:, 1] - 1.0
    eta_a = 2.0 * _CORNERS[:, 0] - 1.0
    pts = [(xi, eta) for eta in _GAUSS for xi in _GAUSS]
    n = np.empty((4, 4))
    dn = np.empty((4, 4, 2))
    for q, (xi, eta) in enumerate(pts):
        n[q] = 0.25 * (1 + xi_a * xi) * (1 + eta_a * eta)
        dn[q, :, 0] = 0.25 * xi_a * (1 + eta_a * eta) * 2.0 / hu
        dn[q, :, 1] = 0.25 * eta_a * (1 + xi_a * xi) * 2.0 / hv
    return n, dn, 0.25 * hu * hv


class _Assembly:
    """Index arrays of one grid: element → node maps, the CSR pattern of the Hessian and the map
    from element-matrix entries to CSR slots (so assembly is one bincount)."""

    def __init__(self, grid: SheetGrid, active: np.ndarray | None):
        nv, nu = grid.nv, grid.nu
        self.nn = nv * nu
        ev, eu = np.meshgrid(np.arange(nv - 1), np.arange(nu - 1), indexing="ij")
        if active is None:
            active = np.ones((nv - 1, nu - 1), bool)
        active = np.asarray(active, bool)
        if active.shape != (nv - 1, nu - 1):
            raise ValueError(f"active element mask must be {(nv - 1, nu - 1)}, got {active.shape}")
        self.active = active
        ev, eu = ev[active], eu[active]
        self.elements = (ev[:, None] + _CORNERS[None, :, 0]) * nu + (eu[:, None] + _CORNERS[None, :, 1])  # (E, 4)
        self.n, self.dn, self.w = _shape_functions(grid.hu, grid.hv)
        dofs = (3 * self.elements[:, :, None] + np.arange(3)).reshape(-1, 12)  # (E, 12)
        rows = np.repeat(dofs, 12, axis=1).ravel()
        cols = np.tile(dofs, (1, 12)).ravel()
        # node (3×3) blocks for nodal terms, and the constant bending matrix
        node_dofs = (3 * np.arange(self.nn)[:, None] + np.arange(3)).reshape(-1, 3)
        nrows = np.repeat(node_dofs, 3, axis=1).ravel()
        ncols = np.tile(node_dofs, (1, 3)).ravel()
        all_rows = np.concatenate([rows, nrows])
        all_cols = np.concatenate([cols, ncols])
        ndof = 3 * self.nn
        key = all_rows.astype(np.int64) * ndof + all_cols
        uniq, inverse = np.unique(key, return_inverse=True)
        self.pattern_rows = (uniq // ndof).astype(np.int32)
        self.pattern_cols = (uniq % ndof).astype(np.int32)
        self.nnz = uniq.size
        self.map_elem = inverse[: rows.size]
        self.map_node = inverse[rows.size:]
        self.ndof = ndof
        # lumped nodal areas (quarter of each active element)
        area = np.zeros(self.nn)
        np.add.at(area, self.elements.ravel(), 0.25 * grid.hu * grid.hv)
        self.node_area = area
        self.has_film = area > 0

    def matrix(self, elem: np.ndarray | None, node: np.ndarray | None) -> sp.csr_matrix:
        data = np.zeros(self.nnz)
        if elem is not None:
            data += np.bincount(self.map_elem, weights=elem.ravel(), minlength=self.nnz)
        if node is not None:
            data += np.bincount(self.map_node, weights=node.ravel(), minlength=self.nnz)
        return sp.csr_matrix((data, (self.pattern_rows, self.pattern_cols)), shape=(self.ndof, self.ndof))


def _bending_operator(grid: SheetGrid, material: SheetMaterial, film: np.ndarray) -> sp.csr_matrix:
    """K_b ⊗ I₃ of the quadratic bending energy (scalar node matrix times the identity on xyz),
    second differences at every node whose eight neighbours are all film (``film`` (nn,) bool)."""
    nv, nu = grid.nv, grid.nu
    hu, hv = grid.hu, grid.hv
    nn = nv * nu
    idx = np.arange(nn).reshape(nv, nu)
    f2 = film.reshape(nv, nu)
    ok = np.ones((nv - 2, nu - 2), bool)
    for dv in (0, 1, 2):
        for du in (0, 1, 2):
            ok &= f2[dv:nv - 2 + dv, du:nu - 2 + du]
    inner = idx[1:-1, 1:-1][ok]
    k = inner.size

    def stencil(offsets: list[tuple[int, int, float]]) -> sp.csr_matrix:
        rows, cols, vals = [], [], []
        iv, iu = np.divmod(inner, nu)
        for dv, du, c in offsets:
            rows.append(np.arange(k))
            cols.append((iv + dv) * nu + (iu + du))
            vals.append(np.full(k, c))
        return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(k, nn))

    duu = stencil([(0, -1, 1 / hu**2), (0, 0, -2 / hu**2), (0, 1, 1 / hu**2)])
    dvv = stencil([(-1, 0, 1 / hv**2), (0, 0, -2 / hv**2), (1, 0, 1 / hv**2)])
    c = 1.0 / (4 * hu * hv)
    duv = stencil([(1, 1, c), (1, -1, -c), (-1, 1, -c), (-1, -1, c)])
    d, nu_p = material.bending_stiffness, material.poisson
    lap = duu + dvv
    k1 = d * hu * hv * (lap.T @ lap - (1 - nu_p) * (duu.T @ dvv + dvv.T @ duu) + 2 * (1 - nu_p) * (duv.T @ duv))
    return sp.kron(k1, sp.eye(3), format="csr")


def membrane_green_strain(grid: SheetGrid, positions: np.ndarray) -> np.ndarray:
    """Green strain (nv−1, nu−1, 2, 2) at the centre of every element (a check of the solution)."""
    x = np.asarray(positions, float)
    xu = 0.5 * ((x[:-1, 1:] - x[:-1, :-1]) + (x[1:, 1:] - x[1:, :-1])) / grid.hu
    xv = 0.5 * ((x[1:, :-1] - x[:-1, :-1]) + (x[1:, 1:] - x[:-1, 1:])) / grid.hv
    f = np.stack([xu, xv], axis=-1)
    return 0.5 * (np.einsum("...ki,...kj->...ij", f, f) - np.eye(2))


class _Energy:
    """The total energy of one problem, its exact gradient and the Newton matrix."""

    def __init__(self, problem: SheetProblem):
        self.p = problem
        self.grid = problem.grid
        self.asm = _Assembly(problem.grid, problem.active)
        mat = problem.material
        self.lam, self.mu = mat.lame()
        lam, mu = self.lam, self.mu
        self.dvoigt = np.array([[lam + 2 * mu, lam, 0.0], [lam, lam + 2 * mu, 0.0], [0.0, 0.0, mu]])
        self.kb = _bending_operator(problem.grid, mat, self.asm.has_film)
        h = min(problem.grid.hu, problem.grid.hv)
        self.penalty = problem.penalty if problem.penalty is not None else 1e2 * mat.membrane_stiffness / h**2
        self.onset = 1e-2  # mm: the unilateral penalty's smoothing band (contact forces start 10 µm out)
        ref = problem.reference if problem.reference is not None else problem.grid.uv()
        self.reference = np.asarray(ref, float).reshape(-1, 2)

    # -- pieces ------------------------------------------------------------------------
    def _kinematics(self, x: np.ndarray):
        xe = x[self.asm.elements]  # (E, 4, 3)
        f = np.einsum("eai,qaj->eqij", xe, self.asm.dn)  # (E, Q, 3, 2)
        return xe, f

    def _membrane(self, f: np.ndarray, hessian: bool):
        c = np.einsum("eqki,eqkj->eqij", f, f)
        e = 0.5 * (c - np.eye(2))
        tr = e[..., 0, 0] + e[..., 1, 1]
        s = self.lam * tr[..., None, None] * np.eye(2) + 2.0 * self.mu * e
        w = self.asm.w
        energy = w * float(np.sum(0.5 * self.lam * tr**2 + self.mu * np.einsum("...ij,...ij->...", e, e)))
        p = f @ s  # (E, Q, 3, 2)
        grad_e = w * np.einsum("eqij,qaj->eai", p, self.asm.dn)  # (E, 4, 3)
        if not hessian:
            return energy, grad_e, None
        dn = self.asm.dn
        b = np.empty(f.shape[:2] + (4, 3, 3))  # (E, Q, a, voigt, xyz)
        b[..., 0, :] = dn[None, :, :, 0, None] * f[:, :, None, :, 0]
        b[..., 1, :] = dn[None, :, :, 1, None] * f[:, :, None, :, 1]
        b[..., 2, :] = dn[None, :, :, 0, None] * f[:, :, None, :, 1] + dn[None, :, :, 1, None] * f[:, :, None, :, 0]
        db = np.einsum("vw,eqawj->eqavj", self.dvoigt, b)
        kmat = w * np.einsum("eqavi,eqbvj->eaibj", b, db)
        # geometric stiffness with the stress's positive part (keeps the matrix semi-definite)
        s_pos = _positive_part_2x2(s)
        g = w * np.einsum("qai,eqij,qbj->eab", dn, s_pos, dn)
        kmat += g[:, :, None, :, None] * np.eye(3)[None, None, :, None, :]
        return energy, grad_e, kmat.reshape(-1, 12, 12)

    def _balloon(self, x: np.ndarray, xe: np.ndarray, f: np.ndarray, hessian: bool):
        bal = self.p.balloon
        assert bal is not None  # called only for a problem with a balloon
        xq = np.einsum("qa,eai->eqi", self.asm.n, xe) - np.asarray(bal.centre, float)
        a, b = f[..., 0], f[..., 1]
        t, pr = bal.tension, bal.pressure
        w = self.asm.w

        def dens_grad(xq, a, b):
            cr = np.cross(a, b)
            j = np.maximum(np.linalg.norm(cr, axis=-1), 1e-300)
            nh = cr / j[..., None]
            gx = -(pr / 3.0) * cr
            ga = t * np.cross(b, nh) - (pr / 3.0) * np.cross(b, xq)
            gb = t * np.cross(nh, a) - (pr / 3.0) * np.cross(xq, a)
            return j, cr, np.stack([gx, ga, gb], axis=-2)  # (..., 3 kinds, 3)

        j, cr, gd = dens_grad(xq, a, b)
        energy = w * float(np.sum(t * j - (pr / 3.0) * np.einsum("...i,...i->...", xq, cr)))
        m = np.stack([np.broadcast_to(self.asm.n, self.asm.dn.shape[:2]), self.asm.dn[..., 0], self.asm.dn[..., 1]], axis=-1)  # (Q, a, kind)
        grad_e = w * np.einsum("qak,eqki->eai", m, gd)
        if not hessian:
            return energy, grad_e, None
        # 9×9 density Hessian by central differences of the exact density gradient
        eps = 1e-6 * max(1.0, float(np.abs(xe).max()))
        hq = np.empty(gd.shape[:2] + (3, 3, 3, 3))  # (E, Q, kind_i, i, kind_j, j)
        base = [xq, a, b]
        for kind in range(3):
            for comp in range(3):
                plus = [v.copy() for v in base]
                minus = [v.copy() for v in base]
                plus[kind][..., comp] += eps
                minus[kind][..., comp] -= eps
                hq[..., kind, comp] = (dens_grad(*plus)[2] - dens_grad(*minus)[2]) / (2 * eps)
        # hq[..., l, j, k, i] holds d grad[k,i] / d var[l,j]; symmetrise
        hq = np.einsum("eqljki->eqkilj", hq)
        hq = 0.5 * (hq + np.einsum("eqkilj->eqljki", hq))
        kel = w * np.einsum("qak,eqkilj,qbl->eaibj", m, hq, m)
        return energy, grad_e, kel.reshape(-1, 12, 12)

    def _contacts(self, x: np.ndarray, hessian: bool):
        area = self.asm.node_area
        k = self.penalty
        energy = 0.0
        grad = np.zeros_like(x)
        hess = np.zeros((x.shape[0], 3, 3)) if hessian else None
        for body in self.p.contacts:
            g, dg = body.gap(x, self.p.time)
            if body.bilateral:
                e, de, dde = 0.5 * g * g, g, np.ones_like(g)
            else:
                e, de, dde = _onset(g, self.onset)
            energy += k * float(np.sum(area * e))
            grad += (k * area * de)[:, None] * dg
            if hessian:
                hess += (k * area * dde)[:, None, None] * dg[:, :, None] * dg[:, None, :]
        if self.p.foundation > 0:
            kt = self.p.foundation * area
            d = x[:, :2] - self.reference
            energy += 0.5 * float(np.sum(kt[:, None] * d * d))
            grad[:, :2] += kt[:, None] * d
            if hess is not None:
                hess[:, 0, 0] += kt
                hess[:, 1, 1] += kt
        return energy, grad, hess

    # -- totals ------------------------------------------------------------------------
    def evaluate(self, xflat: np.ndarray, hessian: bool = True):
        x = xflat.reshape(-1, 3)
        xe, f = self._kinematics(x)
        e_m, ge, ke = self._membrane(f, hessian)
        energy = e_m
        grad = np.zeros_like(x)
        np.add.at(grad, self.asm.elements, ge)
        if self.p.balloon is not None:
            e_b, gb, kb_el = self._balloon(x, xe, f, hessian)
            energy += e_b
            np.add.at(grad, self.asm.elements, gb)
            if hessian:
                ke = ke + kb_el
        e_c, gc, hc = self._contacts(x, hessian)
        energy += e_c
        grad += gc
        kbx = self.kb @ xflat
        energy += 0.5 * float(xflat @ kbx)
        g = grad.ravel() + kbx
        if not hessian:
            return energy, g, None
        return energy, g, self.asm.matrix(ke, hc) + self.kb


def _onset(g: np.ndarray, delta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A unilateral penalty per unit stiffness that is twice differentiable: its curvature rises
    linearly from 0 at a gap of ``delta`` to 1 at contact and stays 1 inside (so Newton does not
    chatter on nodes at the edge of a contact patch); value, slope and curvature at gaps g."""
    inside = g < 0
    band = (g >= 0) & (g < delta)
    r = np.where(band, delta - g, 0.0)
    e = np.where(inside, delta * delta / 6 - 0.5 * delta * g + 0.5 * g * g, r**3 / (6 * delta))
    de = np.where(inside, g - 0.5 * delta, -r * r / (2 * delta))
    dde = np.where(inside, 1.0, r / delta)
    return e, de, dde


def _positive_part_2x2(s: np.ndarray) -> np.ndarray:
    """Symmetric 2×2 matrices with their negative eigenvalues set to zero."""
    a, b, d = s[..., 0, 0], s[..., 0, 1], s[..., 1, 1]
    mean = 0.5 * (a + d)
    rad = np.sqrt(np.maximum(0.25 * (a - d) ** 2 + b * b, 0.0))
    l1, l2 = mean + rad, mean - rad
    # eigenvector of l1: (b, l1 − a) or (l1 − d, b), whichever is better conditioned
    v1 = np.stack([b, l1 - a], axis=-1)
    alt = np.stack([l1 - d, b], axis=-1)
    use_alt = np.linalg.norm(alt, axis=-1) > np.linalg.norm(v1, axis=-1)
    v1 = np.where(use_alt[..., None], alt, v1)
    nrm = np.linalg.norm(v1, axis=-1)
    degenerate = nrm < 1e-300
    v1 = np.where(degenerate[..., None], np.array([1.0, 0.0]), v1 / np.where(degenerate, 1.0, nrm)[..., None])
    v2 = np.stack([-v1[..., 1], v1[..., 0]], axis=-1)
    p1 = np.maximum(l1, 0.0)[..., None, None] * v1[..., :, None] * v1[..., None, :]
    p2 = np.maximum(l2, 0.0)[..., None, None] * v2[..., :, None] * v2[..., None, :]
    return p1 + p2


def _nested_dissection(nv: int, nu: int, separator: int = 2, leaf: int = 64) -> np.ndarray:
    """Node order of geometric nested dissection on the grid (separators two nodes wide, since
    the bending stencil reaches two nodes): the sparse factor then fills like n·log n."""
    idx = np.arange(nv * nu).reshape(nv, nu)
    out: list[np.ndarray] = []

    def rec(block: np.ndarray) -> None:
        r, c = block.shape
        if r * c <= leaf or min(r, c) <= separator:
            out.append(block.ravel())
            return
        if c >= r:
            m = c // 2 - separator // 2
            rec(block[:, :m])
            rec(block[:, m + separator:])
            out.append(block[:, m:m + separator].ravel())
        else:
            m = r // 2 - separator // 2
            rec(block[:m])
            rec(block[m + separator:])
            out.append(block[m:m + separator].ravel())
    rec(idx)
    return np.concatenate(out)


class _Matrix:
    """A Newton matrix: sparse part plus a low-rank part W·diag(c)·Wᵀ (the rigid-motion hold)."""

    def __init__(self, sparse: sp.csr_matrix, w: np.ndarray | None, c: np.ndarray | None):
        self.sparse, self.w, self.c = sparse, w, c

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        y = self.sparse @ x
        if self.w is not None:
            y += self.w @ (self.c * (self.w.T @ x))
        return y


class _Factor:
    """Sparse LU of the free block in nested-dissection order (no pivoting: the matrix is
    symmetric positive definite after the shift), the low-rank part by Woodbury's identity."""

    def __init__(self, a: _Matrix):
        self.lu = splu(a.sparse.tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0,
                       options=dict(SymmetricMode=True))
        self.w = a.w
        if a.w is not None:
            self.sw = self.lu.solve(a.w)  # S⁻¹W
            self.small = np.linalg.inv(np.diag(1.0 / cast(np.ndarray, a.c)) + a.w.T @ self.sw)  # c comes with w

    def solve(self, b: np.ndarray) -> np.ndarray:
        x = self.lu.solve(b)
        if self.w is not None:
            x -= self.sw @ (self.small @ (self.w.T @ x))
        return x


def _pcg(a: _Matrix, b: np.ndarray, m: _Factor, rtol: float, maxiter: int) -> tuple[np.ndarray | None, int]:
    """Conjugate gradients on a x = b preconditioned by the factor of a nearby matrix; None when
    it meets negative curvature or does not reach ``rtol`` within ``maxiter``."""
    x = m.solve(b)
    r = b - a @ x
    bnorm = float(np.linalg.norm(b))
    if bnorm == 0.0:
        return x, 0
    z = m.solve(r)
    p = z.copy()
    rz = float(r @ z)
    for k in range(1, maxiter + 1):
        if np.linalg.norm(r) <= rtol * bnorm:
            return x, k - 1
        ap = a @ p
        curv = float(p @ ap)
        if curv <= 0:
            return None, k
        alpha = rz / curv
        x += alpha * p
        r -= alpha * ap
        z = m.solve(r)
        rz_new = float(r @ z)
        p = z + (rz_new / rz) * p
        rz = rz_new
    return (x, maxiter) if np.linalg.norm(r) <= rtol * bnorm else (None, maxiter)


class _Coordinates:
    """The solver's unknowns.  Without a mold: every node's (x, y, z).  On a mold: every node's
    (x, y), its z = f(x, y, t) exactly (frictionless bilateral contact as a constraint rather
    than a penalty, so large sliding never leaves the surface)."""

    def __init__(self, problem: SheetProblem, nn: int):
        self.mold = problem.mold
        self.t = problem.time
        self.nn = nn
        self.k = 3 if self.mold is None else 2

    def lift(self, y: np.ndarray) -> np.ndarray:
        if self.mold is None:
            return y
        q = y.reshape(-1, 2)
        f, _, _ = self.mold(q, self.t)
        return np.concatenate([q, f[:, None]], axis=1).ravel()

    def reduce(self, x: np.ndarray) -> np.ndarray:
        return x if self.mold is None else x.reshape(-1, 3)[:, :2].ravel()

    def pull_back(self, y: np.ndarray, g: np.ndarray, hmat: sp.csr_matrix | None):
        """Gradient and Newton matrix in the unknowns from those in the positions."""
        if self.mold is None:
            return g, hmat
        q = y.reshape(-1, 2)
        _, grad, hess = self.mold(q, self.t)
        gx = g.reshape(-1, 3)
        gq = (gx[:, :2] + gx[:, 2:3] * grad).ravel()
        if hmat is None:
            return gq, None
        nn = self.nn
        rows = np.concatenate([3 * np.arange(nn), 3 * np.arange(nn) + 1, 3 * np.arange(nn) + 2, 3 * np.arange(nn) + 2])
        cols = np.concatenate([2 * np.arange(nn), 2 * np.arange(nn) + 1, 2 * np.arange(nn), 2 * np.arange(nn) + 1])
        vals = np.concatenate([np.ones(nn), np.ones(nn), grad[:, 0], grad[:, 1]])
        jac = sp.csr_matrix((vals, (rows, cols)), shape=(3 * nn, 2 * nn))
        # the mold's curvature times the normal force: it sets the stiffness of sliding modes, so
        # it stays exact (an indefinite matrix is met by the solver's shift)
        curv = gx[:, 2, None, None] * hess
        r2 = np.repeat((2 * np.arange(nn))[:, None] + np.arange(2), 2, axis=1).ravel()
        c2 = np.tile((2 * np.arange(nn))[:, None] + np.arange(2), (1, 2)).ravel()
        hq = (jac.T @ hmat @ jac) + sp.csr_matrix((curv.ravel(), (r2, c2)), shape=(2 * nn, 2 * nn))
        return gq, hq.tocsr()


def solve(problem: SheetProblem, x0: np.ndarray, tol: float | None = None, max_iter: int = 200,
          log: Callable[[str], None] | None = None, warm: Solution | None = None) -> Solution:
    """Minimise the sheet's energy from the start ``x0`` (nv, nu, 3); degrees of freedom marked in
    ``problem.fixed`` keep ``x0``'s values (on a mold only x and y can be fixed: z follows the
    mold).  ``warm``, the solution of a nearby problem with the same free degrees of freedom,
    lends its last factor as the first preconditioner.  Raises :class:`MechanicsError` when the largest free force does not fall below ``tol``
    (default 1e-9·Y·h, N) within ``max_iter`` Newton steps.

    Each Newton system is solved by conjugate gradients preconditioned with a sparse factor of an
    earlier Newton matrix (refactorised when that takes more than a few iterations, or directly
    when the matrix is not positive definite), which costs a fraction of a factorisation a step."""
    started = time.perf_counter()
    grid = problem.grid
    x0 = np.asarray(x0, float)
    if x0.shape != (grid.nv, grid.nu, 3):
        raise ValueError(f"start positions must be {(grid.nv, grid.nu, 3)}, got {x0.shape}")
    if not np.all(np.isfinite(x0)):
        raise ValueError("start positions contain NaN or infinity")
    en = _Energy(problem)
    coords = _Coordinates(problem, en.asm.nn)
    k = coords.k
    fixed = np.zeros((grid.nv, grid.nu, 3), bool) if problem.fixed is None else np.asarray(problem.fixed, bool)
    if fixed.shape != x0.shape:
        raise ValueError(f"fixed mask must be {x0.shape}, got {fixed.shape}")
    fixed_full = fixed.reshape(-1, 3) | ~en.asm.has_film[:, None]
    fixed = fixed_full[:, :k]  # nodes outside the film do nothing
    order = (k * _nested_dissection(grid.nv, grid.nu)[:, None] + np.arange(k)).ravel()
    free = order[~fixed.ravel()[order]]
    if free.size == 0:
        raise ValueError("every degree of freedom is fixed: nothing to solve")
    h = min(grid.hu, grid.hv)
    scale = problem.material.membrane_stiffness * h
    tol = 1e-9 * scale if tol is None else float(tol)

    # a start that penetrates a body (the body moved since the last frame) starts on its surface
    start = x0.reshape(-1, 3)
    for body in problem.contacts:
        start = np.where(fixed_full, start, body.project(start, problem.time))
    y = coords.reduce(start.ravel()).copy()
    # the film's mean in-plane translation and rotation held at the start's (frictionless films
    # on a mold are otherwise free to drift or turn): three stiff constraints of rank one each
    hold_w = hold_c = None
    if problem.hold_rigid:
        area = en.asm.node_area
        xy = y.reshape(-1, k)[:, :2]
        centre = (area[:, None] * xy).sum(0) / area.sum()
        rel = xy - centre
        w = np.zeros((y.size, 3))
        w[0::k, 0] = area / area.sum()
        w[1::k, 1] = area / area.sum()
        w[0::k, 2] = -area * rel[:, 1]
        w[1::k, 2] = area * rel[:, 0]
        w[:, 2] /= float(np.sum(area * np.sum(rel * rel, axis=1)))
        size2 = float(np.sum(rel * rel * area[:, None]) / area.sum())
        total = problem.material.membrane_stiffness * float(area.sum())
        hold_c = np.array([1e4 * total / size2, 1e4 * total / size2, 1e4 * total])
        unknown = set(problem.hold_rigid) - {"x", "y", "turn"}
        if unknown:
            raise ValueError(f"hold_rigid takes 'x', 'y' and 'turn', got {sorted(unknown)}")
        keep = [i for i, mode in enumerate(("x", "y", "turn")) if mode in problem.hold_rigid]
        w, hold_c = w[:, keep], hold_c[keep]
        hold_w, hold_y = w, y.copy()
        hold_wf = w[free]

    def evaluate(y: np.ndarray, hessian: bool = True):
        e, g, hm = en.evaluate(coords.lift(y), hessian)
        g, hm = coords.pull_back(y, g, hm)
        if hold_w is not None:
            dev = hold_w.T @ (y - hold_y)
            e += 0.5 * float(np.sum(hold_c * dev * dev))
            g = g + hold_w @ (hold_c * dev)
        return e, g, hm

    energy, g, hmat = evaluate(y)
    eye = sp.identity(free.size, format="csr")
    shift = 0.0
    diag_scale = scale / h  # a stiffness (N/mm) per degree of freedom
    factor: _Factor | None = None
    if warm is not None and warm.free is not None and np.array_equal(warm.free, free):
        factor = warm.preconditioner
    previous = math.inf
    stalled = 0
    it = 0
    for it in range(1, max_iter + 1):
        gf = g[free]
        if not np.all(np.isfinite(gf)):
            raise MechanicsError("the sheet's forces became non-finite (a body penetrated too far?)")
        gmax = float(np.max(np.abs(gf)))
        if gmax < tol:
            it -= 1
            break
        if gmax > 0.25 * previous:
            # slow progress: soft modes (sliding, rotation) need the exact Newton step
            factor = None
            stalled += 1
            if stalled >= 20 and gmax < 100.0 * tol:
                break  # round-off floor: forces of ~1e-7·Y·h move no point by 1e-8 mm
        else:
            stalled = 0
        previous = gmax
        hff = hmat[free][:, free].tocsr()
        accepted = False
        for _attempt in range(30):
            a = _Matrix(hff + eye * (shift * diag_scale) if shift > 0 else hff,
                        hold_wf if hold_w is not None else None, hold_c)
            step = None
            if factor is not None:
                # inexact Newton: a forcing term that tightens as the forces fall
                step, used = _pcg(a, -gf, factor, rtol=min(1e-2, 1e-1 * math.sqrt(gmax / scale)), maxiter=30)
                if step is None or used > 15:
                    factor = None
            if step is None:
                try:
                    factor = _Factor(a)
                    step = -factor.solve(gf)
                except RuntimeError:
                    factor, step = None, None
            slope = float(gf @ step) if step is not None and np.all(np.isfinite(step)) else math.inf
            if slope >= 0:
                shift = max(10.0 * shift, 1e-8)
                factor = None
                continue
            alpha = 1.0
            while alpha > 1e-3:
                trial = y.copy()
                trial[free] += alpha * cast(np.ndarray, step)  # a descent direction: not None
                e_new, g_new, _ = evaluate(trial, hessian=False)
                # near the minimum the energy change is below its round-off: judge by the forces
                tiny = abs(slope) * alpha < 1e-12 * max(abs(energy), 1e-30)
                if (e_new <= energy + 1e-4 * alpha * slope) or (
                    tiny and np.max(np.abs(g_new[free])) <= gmax
                ):
                    accepted = True
                    break
                alpha *= 0.5
            if accepted:
                break
            shift = max(10.0 * shift, 1e-8)
            factor = None
        if not accepted:
            raise MechanicsError(
                f"no descent step after {it} Newton steps (largest free force {gmax:.3g} N)"
            )
        y = trial
        if log is not None:
            log(f"newton {it}: largest force {gmax:.3e} N, step {alpha:g}, shift {shift:.1e}, energy {energy:.12g} N·mm")
        if shift > 0:
            shift = shift / 10.0 if shift > 1e-12 else 0.0
        energy, g, hmat = evaluate(y)
    else:
        raise MechanicsError(
            f"no equilibrium after {max_iter} Newton steps: largest free force "
            f"{np.max(np.abs(g[free])):.3g} N > {tol:.3g} N"
        )
    x = coords.lift(y).reshape(grid.nv, grid.nu, 3)
    return Solution(grid, x, energy, it, float(np.max(np.abs(g[free]))), time.perf_counter() - started,
                    factor, free)
