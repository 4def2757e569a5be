"""Compiled per-frame kernels (reconstruction/kernels.py) against the numpy reference
(engine.py), their determinism across processes, and their cache fallback."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import textwrap

import numpy as np
import pytest
from conftest import python_for_other_users

from skinmap.emulator import physics as ph
from skinmap.emulator.scenes import parse_scene_spec
from skinmap.reconstruction import Reconstructor, kernels
from skinmap.reconstruction.engine import metric_terms, unit_data
from skinmap.reconstruction.forward import GaugeLayout, Patches, surface_strains
from skinmap.reconstruction.grid import FineGrid
from skinmap.reconstruction.membrane import read_twist
from skinmap.reconstruction.surface import Surface

PITCH, H, G = 12.0, 0.2, 10.0
NOISE = 0.0057e-2

pytestmark = pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")


def _shapes(rng: np.random.Generator, k: int) -> list:
    """``k`` random shapes cycling through the classes whose reconstruction takes different
    paths (no twist, a twist from the curvature product, from the stretch pattern, from the
    shear; large bends)."""
    def signed(lo, hi):
        return float(rng.uniform(lo, hi) * rng.choice([-1.0, 1.0]))

    makers = [
        lambda: ph.GaussianBumps(height=signed(1, 5), fwhm=float(rng.uniform(15, 30)), centre=tuple(rng.uniform(-20, 20, 2))),
        lambda: ph.Saddle(signed(40, 120)),
        lambda: ph.Saddle(signed(50, 120), axis_angle=float(rng.choice([-30.0, -15.0, 15.0, 30.0, 45.0]))),
        lambda: ph.Cylinder(signed(25, 100), axis_angle=float(rng.uniform(0, 90))),
        lambda: ph.SphereCap(signed(40, 120)),
        lambda: ph.Flat(),
    ]
    return [makers[i % len(makers)]() for i in range(k)]


def _frames(n: int, m: int, k: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Noisy strains of random shapes; every third frame has one or two dead gauges."""
    rng = np.random.default_rng(seed)
    out = []
    for i, shape in enumerate(_shapes(rng, k)):
        eu, el = ph.gauge_strains(shape, n, m, PITCH, H, H, G)
        eu = eu + rng.normal(0, NOISE, eu.shape)
        el = el + rng.normal(0, NOISE, el.shape)
        if i % 3 == 2:
            eu.reshape(-1)[rng.choice(eu.size, 1 + i % 2, replace=False)] = np.nan
        out.append((eu, el))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("n, m, k", [(5, 5, 18), (8, 8, 12), (16, 16, 6), (4, 7, 12), (3, 3, 6)])
def test_compiled_kernels_match_the_numpy_reference(n, m, k):
    # the general model's kernels (the graph fit's are compared in test_reconstruction_graphfit.py)
    fast = Reconstructor(n, m, PITCH, H, H, G, graph_fit=False)
    ref = Reconstructor(n, m, PITCH, H, H, G, kernels="numpy", graph_fit=False)
    assert fast.kernels == "compiled" and ref.kernels == "numpy"
    prev_f = prev_r = None
    for eu, el in _frames(n, m, k, seed=100 * n + m):
        a = fast(eu, el, previous=prev_f)
        b = ref(eu, el, previous=prev_r)
        scale = np.abs(b._coeffs[..., 0, :]).max()
        assert np.abs(a._coeffs - b._coeffs).max() <= 1e-10 * scale  # positions and derivatives
        assert np.abs(a.normals - b.normals).max() <= 1e-10
        assert a.diagnostics.twist_constant == pytest.approx(b.diagnostics.twist_constant, rel=1e-12, abs=1e-15)
        assert a.diagnostics.status == b.diagnostics.status
        assert a.diagnostics.extra["kernels"] == "compiled"
        prev_f, prev_r = a, b


@pytest.mark.slow
@pytest.mark.parametrize("shear_passes, corrections", [(0, 0), (1, 2), (3, 1)])
def test_other_pass_counts_match_the_reference(shear_passes, corrections):
    kw = {"shear_passes": shear_passes, "frame_corrections": corrections}
    fast, ref = Reconstructor(5, 6, graph_fit=False, **kw), Reconstructor(5, 6, kernels="numpy", graph_fit=False, **kw)
    for eu, el in _frames(5, 6, 6, seed=shear_passes):
        a, b = fast(eu, el), ref(eu, el)
        assert np.abs(a.nodes - b.nodes).max() <= 1e-10 * np.abs(b.nodes).max()


def test_metric_kernel_equals_the_reference_bit_for_bit():
    """The twist step reads these terms and makes discrete choices from them."""
    grid = FineGrid(5, 5, PITCH, G, sub=4)
    eu, el = _frames(5, 5, 1, seed=3)[0]
    turning, stretch, valid = unit_data(eu, el, H, H, G)
    lam_u, lam_v = grid.field_maps(valid)(turning, stretch)[3:5]
    got = kernels.metric_terms(grid.spacing, kernels.as_field(lam_u), kernels.as_field(lam_v))
    for mine, theirs in zip(got, metric_terms(grid.spacing, lam_u, lam_v)):
        assert np.array_equal(mine, theirs)


def test_band_solve_matches_lapack():
    grid = FineGrid(6, 5, PITCH, G, sub=4)
    a0, b0 = grid.centre
    band = kernels.laplacian_band(grid.incidence, a0 * grid.mf + b0)
    assert np.array_equal(band, kernels.laplacian_band(grid.incidence, a0 * grid.mf + b0, grid.laplacian.band))
    rhs = np.random.default_rng(2).normal(size=(3, grid.nf * grid.mf))
    x = rhs.copy()
    kernels._band_solve(band, x)
    assert np.allclose(x.T, grid.laplacian.solve(np.ascontiguousarray(rhs.T)), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("n, m", [(5, 5), (4, 7), (16, 16)])
def test_compiled_forward_model_equals_the_numpy_one_bit_for_bit(n, m):
    """The posterior check and the defect correction decide on these χ²: the compiled forward
    model (patch data and gauge strains) must read the same bytes as the numpy one."""
    rec = Reconstructor(n, n if n == m else m, PITCH, H, H, G)
    plain = GaugeLayout.build(rec.n, rec.m, PITCH, G, H, H)
    for eu, el in _frames(rec.n, rec.m, 4, seed=11):
        surf = rec(eu, el)
        pos = np.array(surf._coeffs[..., 0, :])
        reference = Surface(pitch=PITCH, fine_u=rec.grid.u, fine_v=rec.grid.v, fine_positions=pos,
                            node_index=(rec.grid.node_rows, rec.grid.node_cols), fine_sigma=None,  # type: ignore[arg-type]
                            diagnostics=None)  # type: ignore[arg-type]
        patches = Patches(pos, rec.grid.u, rec.grid.v, kernels)
        assert np.array_equal(patches._coeffs, reference._coeffs)
        compiled = rec._surface(pos, None, None)
        assert np.array_equal(compiled._coeffs, reference._coeffs)
        # (the nodes and normals of kernels.node_frames: the numpy steps' bytes)
        assert np.array_equal(compiled.nodes, reference.nodes)
        assert np.array_equal(compiled.normals, reference.normals)
        for mine, theirs in zip(surface_strains(patches, rec._layout), surface_strains(reference, plain)):
            assert np.array_equal(mine, theirs)


def test_compiled_twist_reading_equals_the_numpy_one_bit_for_bit():
    """membrane.read_twist's misfit grid by kernels.quartic_grid: the same reading, to the bit,
    on noisy saddles, spheres and bumps (its grid's minimum decides the twist and ν)."""
    rec = Reconstructor(5, 5, PITCH, H, H, G)
    rec.prepare()
    assert rec._membrane is not None
    rng = np.random.default_rng(21)
    read = 0
    for spec in ("saddle:radius=90,axis_angle=75", "sphere:radius=70", "gaussian:height=3,fwhm=18,u0=4,v0=-3"):
        eu, el = ph.gauge_strains(parse_scene_spec(spec, "elastic", 5, 5, PITCH), 5, 5, PITCH, H, H, G)
        for _ in range(3):
            noisy_u, noisy_l = eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape)
            turning, stretch, valid = unit_data(noisy_u, noisy_l, H, H, G)
            k_u, k_v, tau0 = rec._measured_fields(turning, stretch, valid)
            args = (rec._membrane, stretch, valid, k_u, k_v, tau0, rec.grid.inner, (0.3, 0.5), rec._stretch_sd(NOISE))
            plain, compiled = read_twist(*args), read_twist(*args, compiled=kernels)
            assert (plain is None) == (compiled is None)
            if plain is not None:
                read += 1
                assert tuple(compiled) == tuple(plain)
    assert read >= 6
    c = [rng.normal(size=21) * 10.0 ** rng.uniform(-12, 0) for _ in range(5)]
    ms = np.linspace(-3e-3, 3e-3, 401)
    grid = np.empty((21, 401))
    kernels.quartic_grid(*c, ms, grid)
    assert np.array_equal(grid, (((c[0][:, None] * ms + c[1][:, None]) * ms + c[2][:, None]) * ms + c[3][:, None]) * ms
                          + c[4][:, None])


def test_banded_field_maps_equal_the_dense_ones_to_rounding():
    """16×16 takes its fields through the banded factors (cheaper there than the dense maps):
    the same fields as the dense maps it keeps for the uncertainty, to rounding."""
    grid = FineGrid(16, 16, PITCH, G, sub=2)
    valid = np.ones((2, 16, 16), dtype=bool)
    fields = grid.field_maps(valid)
    assert grid.dense_maps and fields.__name__ == "fn"  # the banded closure, not dense_fn
    rng = np.random.default_rng(4)
    turning, stretch = rng.normal(0.0, 1e-3, (2, 16, 16)), 1.0 + rng.normal(0.0, 1e-3, (2, 16, 16))
    curv, stretch_maps, misfit = grid._dense["curv"], grid._dense["stretch"], grid._dense["misfit"]
    dense = (*(curv @ turning.ravel()).reshape(3, grid.nf, grid.mf),
             *(1.0 + (stretch_maps[d] @ (stretch[d].ravel() - 1.0)).reshape(grid.nf, grid.mf) for d in (0, 1)),
             misfit @ turning.ravel())
    for mine, theirs in zip(fields(turning, stretch), dense):
        assert np.abs(mine - theirs).max() <= 1e-9 * max(np.abs(theirs).max(), 1e-12)


def test_layouts_other_than_the_compiled_one_are_converted():
    f = np.arange(12.0).reshape(3, 4)
    assert kernels.as_field(f) is f
    for other in (f.T, f.astype(np.float32), np.asfortranarray(f)):
        conv = kernels.as_field(other)
        assert conv.flags.c_contiguous and conv.dtype == np.float64 and np.array_equal(conv, other)
    ro = f.copy()
    ro.flags.writeable = False
    assert kernels.as_field(ro).flags.writeable


def test_kernels_option_is_checked():
    with pytest.raises(ValueError, match="kernels"):
        Reconstructor(5, 5, kernels="fortran")


# A fresh process reconstructs a fixed sequence of frames and prints a digest of everything a
# frame publishes, plus whether its kernels run with an on-disk cache.
_SCRIPT = textwrap.dedent(
    """
    import hashlib, os, sys
    import numpy as np
    sys.path.insert(0, TESTS_DIR)
    from test_reconstruction_compiled import _frames
    from threadpoolctl import threadpool_limits
    from skinmap.reconstruction import kernels
    threadpool_limits(1)  # as the daemon runs: BLAS's rounding depends on its thread count
    if os.environ.get("BREAK_CACHE_DIR"):
        # the cache directory disappears after import: loading and saving the code fail
        d = os.environ["NUMBA_CACHE_DIR"]
        os.rename(d, d + ".gone")
        open(d, "w").close()
    from skinmap.reconstruction import Reconstructor
    rec = Reconstructor(5, 5)
    digest, prev = hashlib.sha256(), None
    for eu, el in _frames(5, 5, 12, seed=11):
        s = rec(eu, el, previous=prev)
        for arr in (s.nodes, s.normals, s._coeffs, *s.locate(np.array([[1.0, -7.5], [20.0, 3.0]]))):
            digest.update(np.ascontiguousarray(arr).tobytes())
        prev = s
    stats = kernels.surface_positions.stats
    print(rec.kernels, kernels._state["cached"], digest.hexdigest(), kernels._state["cache_dir"],
          "hits" if sum(stats.cache_hits.values()) else "no-hits", f"misses={sum(stats.cache_misses.values())}")
    """
)


TESTS_DIR = os.path.dirname(os.path.abspath(__file__))


def _run(env_extra: dict[str, str], user: int | None = None, python: str = sys.executable,
         tests_dir: str = TESTS_DIR) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env.update(env_extra)
    script = _SCRIPT.replace("TESTS_DIR", repr(tests_dir))
    drop = [] if user is None else ["setpriv", f"--reuid={user}", f"--regid={user}", "--clear-groups"]
    return subprocess.Popen([*drop, python, "-c", script], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd="/")


def _result(proc: subprocess.Popen) -> list[str]:
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err
    return out.split()


@pytest.mark.slow
def test_fresh_processes_agree_bit_for_bit_with_or_without_a_cache(tmp_path):
    """Replay relies on a fresh process reproducing a frame sequence exactly: code loaded from
    the cache, code compiled in memory because no cache location is writable, code whose
    cache vanished after import, and (as root) an unprivileged user with no writable cache
    location or with a cache directory of its own that root filled (the service's
    `CacheDirectory`) all give identical bytes, and none of them fails."""
    broken = tmp_path / "broken"
    broken.mkdir()
    only_user_dir = {"NUMBA_CACHE_LOCATOR_CLASSES": "UserProvidedCacheLocator"}
    first = _result(_run({}))  # the usual cache (next to the package when writable): filled here
    procs = [
        _run({"NUMBA_CACHE_DIR": os.devnull + "/none", **only_user_dir}),  # nowhere writable
        _run({"NUMBA_CACHE_DIR": str(broken), "BREAK_CACHE_DIR": "1", **only_user_dir}),
    ]
    results = [first] + [_result(p) for p in procs]
    assert [r[0] for r in results] == ["compiled"] * 3
    assert [r[1] for r in results] == ["True", "False", "False"]
    assert [r[3] for r in results[1:]] == ["None", "None"]
    assert len({r[2] for r in results}) == 1
    # and the same as this process computes
    import hashlib

    from threadpoolctl import threadpool_limits

    rec, digest, prev = Reconstructor(5, 5), hashlib.sha256(), None
    with threadpool_limits(1):
        for eu, el in _frames(5, 5, 12, seed=11):
            s = rec(eu, el, previous=prev)
            for arr in (s.nodes, s.normals, s._coeffs, *s.locate(np.array([[1.0, -7.5], [20.0, 3.0]]))):
                digest.update(np.ascontiguousarray(arr).tobytes())
            prev = s
    assert digest.hexdigest() == results[0][2]
    if os.geteuid() == 0 and shutil.which("setpriv"):
        # the service's user cannot write the package directory nor has a home: it compiles in
        # memory, or loads what root compiled into a cache directory it owns (from a readable
        # copy of the package when this checkout lies in a private directory)
        with python_for_other_users(TESTS_DIR) as (python, env_extra, copies):
            shared = tempfile.mkdtemp(prefix="skinmap-numba-cache-")
            try:
                fill = _result(_run({"NUMBA_CACHE_DIR": shared, **env_extra}, python=python,
                                    tests_dir=copies[TESTS_DIR]))
                assert fill[:3] == ["compiled", "True", results[0][2]] and fill[3].startswith(shared)
                for root, dirs, files in os.walk(shared):
                    for name in [*dirs, *files]:
                        os.chown(os.path.join(root, name), 65534, 65534)
                os.chown(shared, 65534, 65534)
                nobody = [_run({"HOME": "/nonexistent", **extra, **env_extra}, user=65534, python=python,
                               tests_dir=copies[TESTS_DIR])
                          for extra in ({}, {"NUMBA_CACHE_DIR": shared})]
                uncached, cached = (_result(p) for p in nobody)
            finally:
                shutil.rmtree(shared, ignore_errors=True)
        assert uncached[:4] == ["compiled", "False", results[0][2], "None"]
        assert cached[:3] == ["compiled", "True", results[0][2]]
        assert cached[4:] == ["hits", "misses=0"]


def test_membrane_kernels_match_the_numpy_reference_on_an_elastic_saddle():
    """The stretch pattern's misfit of each twist-family member (reconstruction/membrane.py),
    compiled: the same Gaussian curvature and residuals to rounding, with gauges missing too."""
    from skinmap.emulator import scenes
    from skinmap.reconstruction.membrane import basis_curvature, membrane_maps, stretch_residual

    rec = Reconstructor(5, 5, PITCH, H, H, G)
    shape = scenes.parse_scene_spec("saddle:radius=90,axis_angle=75", "elastic", 5, 5, PITCH)
    eu, el = ph.gauge_strains(shape, 5, 5, PITCH, H, H, G)
    surf = rec(eu, el)
    positions = np.array(surf._coeffs[..., 0, :])
    maps = membrane_maps(rec.grid)
    theirs_k = basis_curvature(maps, positions, rec.grid.spacing)
    mine_k = np.empty_like(theirs_k)
    kernels.basis_curvature(positions, maps.rows, maps.cols, rec.grid.spacing, mine_k)
    assert np.abs(theirs_k).max() > 1e-5  # a saddle: K of order 1/R²
    assert np.allclose(mine_k, theirs_k, rtol=1e-12, atol=1e-18)
    _, stretch, valid = unit_data(eu, el, H, H, G)
    valid = valid.copy()
    valid.reshape(-1)[[3, 31]] = False  # a row gauge and a column gauge dead
    for lo, hi in ((0.3, 0.5), (0.45, 0.45)):
        r_ref, nu_ref = stretch_residual(maps, theirs_k, stretch, valid, (lo, hi))
        r = np.empty(r_ref.size)
        nu = kernels.stretch_residual(maps.ab, mine_k, np.ascontiguousarray(stretch).reshape(-1),
                                      np.ascontiguousarray(valid).reshape(-1), lo, hi, r)
        assert nu == pytest.approx(nu_ref, rel=1e-12)
        assert np.allclose(r, r_ref, rtol=1e-10, atol=1e-14 * np.abs(r_ref).max())


def test_held_elastic_saddle_frames_match_the_numpy_reference():
    """A still elastic saddle streamed warm (the twist refined on its family each frame, its
    sign weighed): compiled and numpy give the same answers to rounding, frame after frame."""
    from skinmap.emulator import scenes

    fast, ref = Reconstructor(5, 5, PITCH, H, H, G), Reconstructor(5, 5, PITCH, H, H, G, kernels="numpy")
    shape = scenes.parse_scene_spec("saddle:radius=90,axis_angle=75", "elastic", 5, 5, PITCH)
    eu, el = ph.gauge_strains(shape, 5, 5, PITCH, H, H, G)
    rng = np.random.default_rng(4)
    prev_f = prev_r = None
    for _ in range(6):
        du, dl = rng.normal(0, NOISE, eu.shape), rng.normal(0, NOISE, el.shape)
        a, b = fast(eu + du, el + dl, previous=prev_f), ref(eu + du, el + dl, previous=prev_r)
        assert "stretch_twist_refined" in a.diagnostics.extra  # the membrane's refinement ran
        assert a.diagnostics.extra.get("stretch_estimate") == b.diagnostics.extra.get("stretch_estimate")
        assert np.abs(a.nodes - b.nodes).max() <= 1e-9 * np.abs(b.nodes).max()
        prev_f, prev_r = a, b


_SIGNATURES_SCRIPT = textwrap.dedent("""
    import json
    import numpy as np
    from skinmap.emulator import physics as ph, scenes
    from skinmap.reconstruction import Reconstructor, kernels

    def signatures():
        return {name: sorted(str(s) for s in getattr(kernels, name).signatures) for name in kernels._ENTRY_POINTS}

    rec = Reconstructor(5, 5)
    warmed = signatures()
    rng = np.random.default_rng(3)
    shapes = [scenes.parse_scene_spec("saddle:radius=90,axis_angle=75", "elastic", 5, 5, 12.0),
              ph.SphereCap(70.0), ph.GaussianBumps(height=3.0, fwhm=18.0, centre=(4.0, -3.0)),
              ph.Cylinder(60.0, axis_angle=30.0)]
    for shape in shapes:
        eu, el = ph.gauge_strains(shape, 5, 5, 12.0, 0.2, 0.2, 10.0)
        prev = None
        for _ in range(3):
            prev = rec(eu + rng.normal(0.0, 5.7e-5, eu.shape), el + rng.normal(0.0, 5.7e-5, el.shape), previous=prev)
            prev.node_sigma, prev.node_scatter_sigma, prev.locate_sigma(np.zeros((2, 2)))
    after = signatures()
    print(json.dumps({name: [s for s in after[name] if s not in warmed[name]] for name in after}))
""")


def test_the_warm_up_compiles_every_signature_the_frames_use():
    """A kernel first called with argument types its warm-up did not use is compiled (or loaded
    from the cache) in the middle of a frame: read-only arrays are such a type to numba, and a
    twist family's members are shared read-only.  Before the warm-up covered them, a held elastic
    saddle's first frame took 1.2 s with an empty cache and 5-10 ms loading from a filled one
    (the emulated palm at 10 Hz: its slowest frame).  In a fresh process (this one has run
    other frames), no frame of these shapes, held or not, adds a signature to any kernel."""
    import json

    proc = subprocess.run([sys.executable, "-c", _SIGNATURES_SCRIPT], capture_output=True, text=True, timeout=600,
                          cwd=TESTS_DIR)
    assert proc.returncode == 0, proc.stderr[-2000:]
    added = json.loads(proc.stdout.strip().splitlines()[-1])
    assert not any(added.values()), added
