"""The simulated drives follow the true machine, not the controller's description (simhost's strut
model factory): per-strut stiffness, carrier mass and centre of gravity with the payload, offsets."""
from __future__ import annotations

import numpy as np
import pytest

from hexacnc.config import load_config
from hexacnc.daemon.simhost import _plant_factory
from hexacnc.sim.truth import parse_truth, synth_truth_doc


def test_coupled_strut_model_of_the_drives_is_the_true_machines():
    cfg = load_config(None)
    doc = synth_truth_doc(cfg, 11, magnitude=2.0)
    doc.setdefault("dynamics", {})["simulated_drives"] = "coupled"
    doc["truth"]["payload_kg"] = 40.0
    truth = parse_truth(doc)
    view = _plant_factory(truth)(2, cfg)              # SimDrives passes the controller's cfg: ignored
    model = view.s.cs.model
    assert np.allclose(model.k, truth.cfg.stiffness_N_per_mm) and not np.allclose(model.k, cfg.stiffness_N_per_mm)
    m = truth.cfg.mass_kg + 40.0
    assert model.mc == pytest.approx(m * 1e-3)
    cog = (truth.cfg.mass_kg * np.asarray(truth.cfg.center_of_gravity_mm) + 40.0 * truth.tip) / m
    assert np.allclose(model.cog, cog)
    assert np.allclose(view.s.off, truth.cfg.strut_offset_mm)   # readings -> true lengths by the true offsets
    assert view.deflection_mm == 0.0                             # at rest


def test_without_a_truth_the_drives_keep_the_controllers_model():
    assert _plant_factory(None) is None
