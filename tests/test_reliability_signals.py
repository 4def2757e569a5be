"""Reliability against bad signals: dead, saturated, NaN and wildly inconsistent gauges.

The reconstruction must degrade gracefully: never raise, never publish NaN, and say per element
how far to trust it (messages.ElementFlag). The pure pipeline is checked directly (fast); the
gateway end to end (emulated scanner → skinmapd → Zenoh subscriber, status and MCAP).
"""
from __future__ import annotations

import json
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from conftest import pipeline_sheet
from hypothesis.extra import numpy as hnp

from skinmap.strains import Calibration, reject_implausible_units
from skinmap.wire.messages import ElementFlag
from skinmap.daemon.pipeline import ArrayGeometry, FramePipeline
from skinmap.emulator.physics import gauge_strains, make_shape
from skinmap.protocol import RES_OPEN, RES_SATURATED, Scan

VALID, EXTRAPOLATED, DEGRADED, STALE = (int(f) for f in (ElementFlag.VALID, ElementFlag.EXTRAPOLATED,
                                                         ElementFlag.DEGRADED, ElementFlag.STALE))
N = M = 5
PITCH = 12.0
GEOMETRY, ELEMENT_UV, GF, R0 = pipeline_sheet(N, M, PITCH)
SHAPE = make_shape("gaussian", height=3.0, fwhm=24.0, u0=4.0, v0=-3.0)
EPS_U, EPS_L = gauge_strains(SHAPE, N, M, pitch=PITCH)


def resistances(eps_upper: np.ndarray, eps_lower: np.ndarray) -> np.ndarray:
    return R0 * (1.0 + GF * np.stack([eps_upper, eps_lower]))


GOOD = resistances(EPS_U, EPS_L)


@pytest.fixture(scope="module")
def warm_pipeline_factory():
    def make() -> FramePipeline:
        return FramePipeline(GEOMETRY, Calibration(GF, R0), ELEMENT_UV, np.zeros(len(ELEMENT_UV)))
    make().process(GOOD, 0, 0, 0)  # first call builds the solver's caches
    return make


def check_publishable(result) -> None:
    """What the gateway publishes from a result is finite, and flags hold only known bits."""
    for name in ("nodes_mm", "normals", "node_sigma_mm", "element_positions_mm", "element_normals", "element_sigma_mm"):
        assert np.isfinite(getattr(result, name)).all(), name
    assert not (result.element_flags & ~np.uint8(VALID | EXTRAPOLATED | DEGRADED | STALE | ElementFlag.AMBIGUOUS)).any()
    # a VALID element's uncertainty is a real estimate, not the 1 m placeholder
    assert (result.element_sigma_mm[(result.element_flags & VALID) != 0] < 1e3).all()


def near_any(element: int, rows: np.ndarray, cols: np.ndarray) -> bool:
    """Whether any of the cells (rows[k], cols[k]) lies within 1.5 pitch of the element."""
    centres = np.stack([(cols - (M - 1) / 2) * PITCH, (rows - (N - 1) / 2) * PITCH], axis=1)
    return bool((np.abs(centres - ELEMENT_UV[element]).max(axis=1) <= 1.5 * PITCH).any())


def near(cell_i: int, cell_j: int) -> np.ndarray:
    """Elements within 1.5 pitch of cell (i, j): the ones a fault there may touch."""
    centre = np.array([(cell_j - (M - 1) / 2) * PITCH, (cell_i - (N - 1) / 2) * PITCH])
    return np.abs(ELEMENT_UV - centre).max(axis=1) <= 1.5 * PITCH


# ---------------------------------------------------------------------------------------------
# the pure pipeline


def test_dead_gauge_degrades_only_elements_near_it(warm_pipeline_factory):
    p = warm_pipeline_factory()
    r = GOOD.copy()
    r[0, 0, 0, 0] = np.nan  # open upper row gauge of the corner cell
    res = p.process(r, 1, 0, 0)
    check_publishable(res)
    assert not res.gauge_valid[0, 0, 0, 0] and res.gauge_valid.sum() == res.gauge_valid.size - 1
    degraded = (res.element_flags & DEGRADED) != 0
    assert degraded[near(0, 0)].all() and not degraded[~near(0, 0)].any()
    assert (res.element_flags & VALID).all()  # the other units of those cells still measure


def test_saturated_and_open_gauges_from_the_wire_sentinels(warm_pipeline_factory):
    wire = np.round(GOOD * 1e6).astype(np.uint32)
    wire[1, 1, 2, 2] = RES_SATURATED
    wire[0, 0, 4, 4] = RES_OPEN
    scan = Scan(7, 1000, 1000, wire)
    res = warm_pipeline_factory().process(scan.resistances_ohm(), 7, 1000, 0)
    check_publishable(res)
    assert not res.gauge_valid[1, 1, 2, 2] and not res.gauge_valid[0, 0, 4, 4]
    assert np.isnan(res.eps_lower[1, 2, 2]) and np.isnan(res.eps_upper[0, 4, 4])
    degraded = (res.element_flags & DEGRADED) != 0
    assert degraded[near(2, 2) | near(4, 4)].all()


@pytest.mark.slow
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf, -5.0, 0.0, 1e12])
def test_non_physical_resistances_are_rejected_per_gauge(warm_pipeline_factory, value):
    r = GOOD.copy()
    r[1, 0, 3, 1] = value
    res = warm_pipeline_factory().process(r, 1, 0, 0)
    check_publishable(res)
    assert not res.gauge_valid[1, 0, 3, 1] and res.gauge_valid.sum() == res.gauge_valid.size - 1


@pytest.mark.slow
def test_every_gauge_dead_gives_flagged_prior_then_recovers(warm_pipeline_factory):
    p = warm_pipeline_factory()
    first = p.process(GOOD, 1, 0, 0)
    dead = p.process(np.full_like(GOOD, np.nan), 2, 25_000, 0)
    check_publishable(dead)
    assert not dead.gauge_valid.any()
    # no measurement anywhere: no element is a current estimate
    assert not (dead.element_flags & VALID).any() and (dead.element_flags & DEGRADED).all()
    back = p.process(GOOD, 3, 50_000, 0)
    check_publishable(back)
    assert (back.element_flags == first.element_flags).all()
    np.testing.assert_allclose(back.element_positions_mm, first.element_positions_mm, atol=1e-6)


def test_a_cell_with_both_layers_of_a_unit_dead_is_still_measured_by_its_other_unit(warm_pipeline_factory):
    r = GOOD.copy()
    r[:, 0, 2, 2] = np.nan  # upper and lower row gauges of the centre cell: the column unit remains
    res = warm_pipeline_factory().process(r, 1, 0, 0)
    check_publishable(res)
    assert (res.element_flags & VALID).all() and ((res.element_flags & DEGRADED) != 0)[near(2, 2)].all()


@pytest.mark.slow
def test_random_30_percent_strains_are_rejected_as_impossible_bends(warm_pipeline_factory):
    p = warm_pipeline_factory()
    good = p.process(GOOD, 1, 0, 0)
    rng = np.random.default_rng(30)
    wild = p.process(resistances(rng.uniform(-0.3, 0.3, (2, N, M)), rng.uniform(-0.3, 0.3, (2, N, M))), 2, 25_000, 0)
    check_publishable(wild)
    assert wild.diagnostics["implausible_units"] > 10
    assert (~wild.gauge_valid).sum() == 2 * wild.diagnostics["implausible_units"]  # both layers of each
    assert ((wild.element_flags & DEGRADED) != 0).all()
    back = p.process(GOOD, 3, 50_000, 0)
    assert (back.element_flags == good.element_flags).all() and back.diagnostics["implausible_units"] == 0


@pytest.mark.slow
def test_plausible_but_mutually_inconsistent_strains_flag_every_element(warm_pipeline_factory):
    rng = np.random.default_rng(31)
    common = rng.uniform(-0.05, 0.05, (2, N, M))
    bend = rng.uniform(-0.12, 0.12, (2, N, M))  # each gauge turns by up to ±3 rad, independently
    res = warm_pipeline_factory().process(resistances(common + bend / 2, common - bend / 2), 1, 0, 0)
    check_publishable(res)
    assert res.diagnostics["implausible_units"] == 0 and res.gauge_valid.all()
    assert res.diagnostics["inconsistent"] is True
    assert ((res.element_flags & DEGRADED) != 0).all()


@pytest.mark.slow
def test_legitimate_shapes_are_not_called_inconsistent():
    for shape in (make_shape("cylinder", radius=10.0, axis_angle=30.0), make_shape("saddle", radius=40.0),
                  make_shape("gaussian", height=8.0, fwhm=14.0), make_shape("sphere", radius=-20.0),
                  make_shape("membrane", fingers=2)):
        eu, el = gauge_strains(shape, N, M, pitch=PITCH)
        p = FramePipeline(GEOMETRY, Calibration(GF, R0), ELEMENT_UV, np.zeros(len(ELEMENT_UV)))
        res = p.process(resistances(eu, el), 1, 0, 0)
        assert res.diagnostics["inconsistent"] is False and res.diagnostics["implausible_units"] == 0, shape


@pytest.mark.slow
def test_upper_and_lower_swapped_everywhere_reads_as_the_mirror_shape(warm_pipeline_factory):
    """A global swap is physically consistent (the sheet bent the other way): undetectable from
    strains alone, documented as such. A partial swap stays finite."""
    good = warm_pipeline_factory().process(GOOD, 1, 0, 0)
    swapped = warm_pipeline_factory().process(resistances(EPS_L, EPS_U), 1, 0, 0)
    check_publishable(swapped)
    np.testing.assert_allclose(swapped.nodes_mm[..., 2], -good.nodes_mm[..., 2], atol=0.05)
    eu, el = EPS_U.copy(), EPS_L.copy()
    eu[:, :, :2], el[:, :, :2] = EPS_L[:, :, :2], EPS_U[:, :, :2]
    check_publishable(warm_pipeline_factory().process(resistances(eu, el), 1, 0, 0))


def test_reject_implausible_units_leaves_its_inputs_alone():
    eu, el = EPS_U.copy(), EPS_L.copy()
    eu[0, 1, 1], el[0, 1, 1] = 0.2, -0.2  # 0.4 strain across 0.4 mm: a 10 rad turn over 10 mm
    valid = np.ones((2, 2, N, M), bool)
    eu2, el2, valid2, count = reject_implausible_units(eu, el, valid, GEOMETRY.gauge_length_mm,
                                                        GEOMETRY.h_upper_mm, GEOMETRY.h_lower_mm)
    assert count == 1 and valid.all() and eu[0, 1, 1] == 0.2
    assert not valid2[:, 0, 1, 1].any() and np.isnan(eu2[0, 1, 1]) and np.isnan(el2[0, 1, 1])
    assert valid2.sum() == valid.size - 2


@pytest.mark.slow
def test_non_finite_solution_holds_the_last_good_frame_as_stale(warm_pipeline_factory, monkeypatch):
    p = warm_pipeline_factory()
    fresh = warm_pipeline_factory()
    good = p.process(GOOD, 1, 0, 0)

    class NanSurface:
        """The real surface with every position NaN: a solver that diverged."""

        def __init__(self, surf):
            self._surf = surf
            self.nodes = np.full_like(np.asarray(surf.nodes), np.nan)

        def locate(self, uv):
            pos, *rest = self._surf.locate(uv)
            return (np.full_like(np.asarray(pos), np.nan), *rest)

        def __getattr__(self, name):
            return getattr(self._surf, name)

    def diverging(pipeline):
        real_rec = pipeline.reconstructor
        return lambda *a, **kw: NanSurface(real_rec(*a, **kw))

    monkeypatch.setattr(p, "reconstructor", diverging(p))
    monkeypatch.setattr(fresh, "reconstructor", diverging(fresh))
    held = p.process(GOOD, 2, 25_000, 0)
    first_ever = fresh.process(GOOD, 1, 0, 0)
    monkeypatch.undo()
    for res in (held, first_ever):
        check_publishable(res)
        assert (res.element_flags & STALE).all()
    np.testing.assert_array_equal(held.element_positions_mm, good.element_positions_mm)
    assert held.seq == 2  # the held shape goes out under the new scan's number, flagged STALE
    assert not (first_ever.element_flags & VALID).any()  # nothing to hold yet: flat prior, not valid


FUZZ_EXAMPLES = 150


@settings(max_examples=FUZZ_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    scale=hnp.arrays(np.float64, (2, 2, N, M),
                     elements=st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                                        st.floats(0.5, 1.5))),
)
@pytest.mark.slow
def test_fuzz_any_resistances_give_a_publishable_result(warm_pipeline_factory, scale):
    """Arbitrary per-gauge factors on a good scan (NaN, ±inf, negative, huge, subnormal, or
    near 1): never raises, never non-finite, flags consistent with the gauges it could use."""
    with np.errstate(all="ignore"):
        r = GOOD * scale
    res = warm_pipeline_factory().process(r, 1, 0, 0)
    check_publishable(res)
    measured_cells = (res.gauge_valid[0] & res.gauge_valid[1]).any(axis=0)  # (N, M)
    for k in range(len(ELEMENT_UV)):
        i, j = np.nonzero(measured_cells)
        has_data = bool(len(i)) and bool(near_any(k, i, j))
        if not has_data:
            assert not res.element_flags[k] & VALID
    assert np.isnan(res.eps_upper[~res.gauge_valid[0]]).all() and np.isnan(res.eps_lower[~res.gauge_valid[1]]).all()


def test_fuzz_count_is_the_one_docs_reliability_quotes():
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[1] / "docs" / "reliability.md").read_text()
    (row,) = [line for line in doc.splitlines() if "test_fuzz_any_resistances_give_a_publishable_result" in line]
    assert f"| {FUZZ_EXAMPLES} per run |" in row, row


# ---------------------------------------------------------------------------------------------
# end to end: emulator → skinmapd → Zenoh


@pytest.mark.slow
def test_dead_and_saturated_gauges_mid_stream_are_flagged_named_and_recovered(tmp_path):
    from test_reliability_serial import Rig, run_fault

    mask = np.zeros((2, 2, N, M), dtype=bool)
    mask[0, 0, 2, 2] = True
    sat = np.zeros_like(mask)
    sat[1, 1, 0, 4] = True
    with Rig(tmp_path, "gauges") as rig:
        rig.wait_streaming()
        emu, gw = rig.emu, rig.gw
        seen: dict = {}

        def inject() -> None:
            emu.set_open(mask)
            emu.set_saturated(sat)

        def watch_flags() -> None:
            st = rig.gw.status()
            seen.setdefault("faults", set()).update(st["device_faults"])

        def clear() -> None:
            watch_flags()
            emu.set_open(np.zeros_like(mask))
            emu.set_saturated(np.zeros_like(sat))

        t_fault = time.time_ns()
        phase = run_fault(gw, rig.sub, "dead gauge + saturated gauge for 1.5 s", inject, clear, 1.5,
                          accept=lambda r: not (r.flags & DEGRADED).any())
        during = [r for r in rig.sub.snapshot() if t_fault + 100_000_000 < r.scan_rx_ns and (r.flags & DEGRADED).any()]
        healthy_again = None
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            st = gw.status()
            if st["healthy"]:
                healthy_again = st
                break
            time.sleep(0.1)
    assert during, "the faulty scans must be published, flagged DEGRADED"
    flagged = (during[-1].flags & DEGRADED) != 0
    near_fault = np.abs(ELEMENT_UV).max(axis=1) <= 18.0
    assert flagged[near_fault].all()
    assert all(r.finite for r in rig.sub.snapshot())
    assert any("unusable" in w for w in phase.warnings)
    assert {"GAUGE_OPEN", "GAUGE_SATURATED"} <= seen["faults"]
    assert healthy_again is not None, "status must return to healthy once the gauges read again"
    _texts, statuses = rig.logged()
    assert any(any("unusable" in w for w in s.get("warnings", [])) for s in statuses)


@pytest.mark.slow
def test_wildly_inconsistent_strains_mid_stream_never_publish_nan(tmp_path):
    from test_reliability_serial import Rig, run_fault

    rng = np.random.default_rng(7)
    with Rig(tmp_path, "wild") as rig:
        rig.wait_streaming()
        device = rig.emu.device

        def wild_strains(_shape_times) -> np.ndarray:
            return rng.uniform(-0.3, 0.3, (2, 2, N, M))

        phase = run_fault(rig.gw, rig.sub, "random ±30 % strains for 1.5 s",
                          lambda: setattr(device, "strains", wild_strains),
                          lambda: delattr(device, "strains"), 1.5,
                          accept=lambda r: not (r.flags & DEGRADED).any())
        t_end = time.time_ns()
    items = rig.sub.snapshot()
    assert all(r.finite for r in items)
    assert any((r.flags & DEGRADED).all() for r in items if r.scan_rx_ns < t_end)
    assert any("unusable" in w for w in phase.warnings)
    print("RELIABILITY " + json.dumps({"fault": phase.fault, "recovery_s": phase.recovery_s,
                                       "published": len(items)}))


def test_clarabel_field_fit_gives_the_factorized_result_and_survives_a_dead_gauge():
    """`[reconstruction] convex_solver = "clarabel"`: the same convex field fit solved by
    Clarabel (Huber loss); with every gauge fitted exactly both solvers give one surface."""
    fast = FramePipeline(GEOMETRY, Calibration(GF, R0), ELEMENT_UV, np.zeros(len(ELEMENT_UV)))
    conic = FramePipeline(GEOMETRY, Calibration(GF, R0), ELEMENT_UV, np.zeros(len(ELEMENT_UV)), convex_solver="clarabel")
    a, b = fast.process(GOOD, 0, 0, 0), conic.process(GOOD, 0, 0, 0)
    assert conic.reconstructor.convex_solver == "clarabel"
    np.testing.assert_allclose(b.element_positions_mm, a.element_positions_mm, atol=5e-3)
    dead = GOOD.copy()
    dead[0, 0, 2, 2] = RES_OPEN
    check_publishable(conic.process(dead, 1, 1000, 1))
    # a reconnect with another solver builds its own reconstructor
    other = FramePipeline(GEOMETRY, Calibration(GF, R0), ELEMENT_UV, np.zeros(len(ELEMENT_UV)))
    other.continue_from(conic)
    assert other.reconstructor.convex_solver == "factorized"


def test_graph_fit_option_reaches_the_reconstructor_and_large_sheets_keep_the_general_model_first():
    """`[reconstruction] graph_fit` (default true): a sharp bump is fitted as a height graph; a
    sheet beyond the graph-first size keeps the general model first (the graph only where it
    misfits) instead of failing."""
    shape = make_shape("gaussian", height=5.0, fwhm=15.0, u0=-14.0, v0=11.0)
    good = resistances(*gauge_strains(shape, N, M, pitch=PITCH))
    plain = FramePipeline(GEOMETRY, Calibration(GF, R0), ELEMENT_UV, np.zeros(len(ELEMENT_UV)), graph_fit=False)
    graph = FramePipeline(GEOMETRY, Calibration(GF, R0), ELEMENT_UV, np.zeros(len(ELEMENT_UV)))
    a, b = plain.process(good, 0, 0, 0), graph.process(good, 0, 0, 0)
    assert graph.reconstructor.graph_fit and not plain.reconstructor.graph_fit
    check_publishable(b)
    truth = shape.position(ELEMENT_UV)
    err = [np.linalg.norm(r.element_positions_mm - r.element_positions_mm[4] - (truth - truth[4]), axis=1).max()
           for r in (a, b)]
    assert err[1] < err[0]  # the graph resolves the sharp bump the general model smooths
    # a reconnect with the other setting builds its own reconstructor
    other = FramePipeline(GEOMETRY, Calibration(GF, R0), ELEMENT_UV, np.zeros(len(ELEMENT_UV)), graph_fit=False)
    other.continue_from(graph)
    assert not other.reconstructor.graph_fit
    big = ArrayGeometry(9, 9, PITCH, 0.2, 0.2)
    large = FramePipeline(big, Calibration(np.full((2, 2, 9, 9), 1.24), np.full((2, 2, 9, 9), 6.55)), ELEMENT_UV,
                          np.zeros(len(ELEMENT_UV)))
    assert not large.reconstructor.graph_fit and large.reconstructor.graph_rescue  # (9×9: where the general model misfits)

