"""The benchmark's Cramér–Rao figure (bench/reconstruction.py, ``noise_floor``): the noise-forced
error of the model linearised about its noise-free answer.  Beside it the benchmark prints the
noisy error, so the figure must describe what the noise does to a real frame: on elastic films
(their twist read from the membrane, a mirror weighed), the Monte-Carlo noisy error is about
√(clean² + CR²), and a frame's linear response does not depend on the difference step."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from skinmap.emulator import physics as ph
from skinmap.emulator import scenes
from skinmap.reconstruction import reconstruct

BENCH = Path(__file__).resolve().parent.parent / "bench"
sys.path.insert(0, str(BENCH))  # its elastic_dataset import
# by path, under its own name: "reconstruction" is also a folder of the package
_spec = importlib.util.spec_from_file_location("bench_reconstruction", BENCH / "reconstruction.py")
assert _spec is not None and _spec.loader is not None
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)

N = 5
SCENES = ("sphere:radius=70", "saddle:radius=90,axis_angle=75", "gaussian:height=3,fwhm=20,u0=6,v0=-4")


def film(spec: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    shape = scenes.parse_scene_spec(spec, "elastic", N, N, bench.PITCH)
    eu, el = ph.gauge_strains(shape, N, N, bench.PITCH, bench.H, bench.H, bench.GAUGE)
    return eu, el, ph.ground_truth(shape, N, N, bench.PITCH).nodes


def draws(seed: int, count: int, shape: tuple[int, ...]) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    return [(rng.normal(0, bench.NOISE, shape), rng.normal(0, bench.NOISE, shape)) for _ in range(count)]


@pytest.mark.parametrize("spec", SCENES)
def test_noise_floor_predicts_the_noisy_error_within_a_fifth(spec: str) -> None:
    eu, el, truth = film(spec)
    clean = bench.node_errors(reconstruct(eu, el, bench.PITCH, bench.H, bench.H, strain_sigma=bench.NOISE).nodes,
                              truth).mean()
    floor = bench.noise_floor(eu, el, draws(1, bench.FLOOR_DRAWS, eu.shape))
    noisy = np.mean([bench.node_errors(reconstruct(eu + du, el + dl, bench.PITCH, bench.H, bench.H).nodes, truth).mean()
                     for du, dl in draws(2, 16, eu.shape)])
    expected = np.hypot(clean, floor)
    assert floor > 0.0
    assert 0.8 <= noisy / expected <= 1.25, (clean, floor, noisy)


def test_noise_floor_is_a_linear_response() -> None:
    """The same figure from steps a hundred times apart: the response is read in the linear
    regime, not from a decision the step flips or from a solver's tolerance."""
    eu, el, _ = film(SCENES[1])
    noise = draws(3, 3, eu.shape)
    small, large = [], []
    for step, out in ((1e-3, small), (1e-1, large)):
        saved, bench.RESPONSE_STEP = bench.RESPONSE_STEP, step
        try:
            out.append(bench.noise_floor(eu, el, noise))
        finally:
            bench.RESPONSE_STEP = saved
    assert small[0] == pytest.approx(large[0], rel=0.02)


def test_noise_floor_says_so_where_a_decision_flips_within_the_step(monkeypatch) -> None:
    """An answer with no linear response (here one that jumps by 1 mm with the sign of the
    data's first gauge, as a flipped decision does) has no Cramér–Rao figure: NaN, printed as
    such, rather than the jump divided by the step."""
    eu, el, _ = film(SCENES[0])
    real = bench.reconstruct

    def flipping(u, lo, *args, **kw):
        surf = real(u, lo, *args, **kw)
        jump = 1.0 if u[0, 0, 0] > eu[0, 0, 0] else 0.0

        class Jumped:
            nodes = surf.nodes + np.array([0.0, 0.0, jump]) * (np.arange(N)[None, :, None] / N)
        return Jumped()

    noise = draws(4, 3, eu.shape)
    assert np.isfinite(bench.noise_floor(eu, el, noise))
    monkeypatch.setattr(bench, "reconstruct", flipping)
    assert np.isnan(bench.noise_floor(eu, el, noise))
    assert bench.floor_text([float("nan"), 0.01]) == "0.0100+" and bench.floor_text([float("nan")]) == "n/l"
