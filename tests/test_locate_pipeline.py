"""Localisation through the pipeline: simulate, then locate, gives the truth back."""

from __future__ import annotations

import numpy as np
import pytest

from echoloc import pipeline
from echoloc.localise.evaluation import evaluate
from echoloc.physics.transducer import PRESETS
from echoloc.sim.scenefile import load_scene
from echoloc.sim.simulation import simulate
from repo_paths import REPO

SCENES = REPO / "src" / "echoloc" / "scenes"


def test_two_transmitters_fired_in_turn_are_located_together() -> None:
    """two-transmitters: from the second frame on every object rests on
    eight ellipsoids (2 transmitters x 4 receivers) and is tighter than on four."""
    recording = simulate(load_scene(SCENES / "two-transmitters.toml"), 6)
    chain = pipeline.prepare(recording)
    assert pipeline.combines_transmitters(chain)
    results = [objects for _, objects in pipeline.run(chain)]
    assert recording.truth_positions_m is not None
    report = evaluate(results, recording.truth_positions_m, match_radius_m=0.005)
    assert report.recall == 1.0
    assert report.n_false == 0
    first, later = results[0], results[1:]
    assert all(len(o.receivers) == 4 for o in first.objects)
    for frame in later:
        for obj in frame.objects:
            assert len(obj.receivers) == 8
            assert sorted(set(obj.transmitters)) == [0, 1]
    single = np.mean([np.trace(o.covariance_m2) for o in first.objects])
    combined = np.mean([np.trace(o.covariance_m2) for f in later for o in f.objects])
    assert combined < 0.8 * single


def test_the_transducers_beam_bounds_what_locate_accepts() -> None:
    """With the 50 kHz preset the recording carries the piston's first-null half-angle,
    sin(theta) = 3.8317 / (k a) (Kinsler, section 7.4), and locate uses it: the third
    ball, outside two receivers' beams, is not invented from other balls' echoes."""
    scene = load_scene(SCENES / "report-three-balls-transducers.toml")
    recording = simulate(scene, 4)
    model = PRESETS[scene.transducer or ""]
    ka = 2 * np.pi * scene.pulse.carrier_hz / scene.speed_of_sound_m_s * model.radius_m
    assert recording.field_of_view_deg == pytest.approx(np.degrees(np.arcsin(3.8317 / ka)), rel=1e-4)
    chain = pipeline.prepare(recording)
    assert chain.locate_options.field_of_view_deg == recording.field_of_view_deg
    results = [objects for _, objects in pipeline.run(chain)]
    assert recording.truth_positions_m is not None
    report = evaluate(results, recording.truth_positions_m, match_radius_m=0.005)
    assert report.n_false == 0
    assert report.n_matched >= 2 * len(results)
