"""The turn drive's acceleration limit: read off a repeat's commands and odometry, and kept by C-/RC-LB-NMPC."""
import dataclasses
import math

import numpy as np
import pytest

from services.bridge.vehicle import _approach
from services.controller.corridor import Corridor
from services.controller.robust_nmpc import RCLBNMPCLaw
from services.controller.settings import NMPCSettings
from services.controller.turn_accel import TurnLead, fit_turn_accel
from tests.test_robust_nmpc import DT, arc_path, ctx_for


def drive(u, tau, limit, noise, seed=4):
    """The odometry of the simulator's own turn drive (services/bridge/vehicle.py) under the commands u
    held per period, at its 10 substeps, with white noise on each reading."""
    rng = np.random.default_rng(seed)
    w, out = 0.0, [0.0]
    for uk in u:
        for _ in range(10):
            w = _approach(w, uk, tau, limit, limit, DT / 10)
        out.append(w + noise * rng.standard_normal())
    return np.array(out)


def corner_commands(amplitude, n=600, seed=2):
    """Turns held for 1-4 s, as a repeat's plans command them through corners and back."""
    rng = np.random.default_rng(seed)
    u = []
    while len(u) < n:
        u += [amplitude * rng.uniform(-1, 1)] * int(rng.integers(10, 40))
    return np.array(u[:n] + [np.nan])


def test_the_fit_reads_the_simulators_turn_acceleration_limit_with_the_models_lag_held():
    u = corner_commands(1.2)
    y = drive(u[:-1], tau=0.35, limit=0.9, noise=0.01)
    fit = fit_turn_accel(u, y, DT, tau_s=0.35)
    assert fit.limit_radps2 == pytest.approx(0.9, rel=0.1) and fit.asking > 50
    assert fit.rmse_radps < 0.5 * fit.rmse_free_radps


def test_a_drive_that_never_met_its_limit_fits_without_one():
    """Gentle turns of a drive with a 7.7 rad/s^2 limit (a Husky): no limit, whatever lag and limit
    together would mimic the lag (fitted freely, a 0.04 s lag with 1.3 rad/s^2 did)."""
    u = corner_commands(0.8)
    y = drive(u[:-1], tau=0.13, limit=7.7, noise=0.01)
    fit = fit_turn_accel(u, y, DT, tau_s=0.13)
    assert math.isinf(fit.limit_radps2) and "no acceleration limit met" in fit.describe()
    assert fit_turn_accel(u[:30], y[:30], DT, tau_s=0.13) is None          # too little to say


def test_the_leads_are_the_commands_less_the_lags_state_worked_by_hand():
    tl = TurnLead(beta=0.5, max_radps=0.3)
    # xi: 0.2, 0.5 * 0.2 + 0.5 * 1 = 0.6, 0.5 * 0.6 + 0.5 * 1 = 0.8
    np.testing.assert_allclose(tl.leads(np.array([1.0, 1.0, 0.0]), 0.2), [0.8, 0.4, -0.8])
    assert TurnLead.of(0.9, 0.4, DT).max_radps == pytest.approx(0.36)
    assert TurnLead.of(None, 0.4, DT) is None and TurnLead.of(math.inf, 0.4, DT) is None
    assert TurnLead.of(0.9, 0.0, DT) is None                             # no lag modelled: nothing to lead
    # brought within the lead in turn: 0.2 + 0.3, then xi = 0.35 -> 0.65, then xi = 0.5 -> 0.2
    np.testing.assert_allclose(tl.followable(np.array([1.0, 1.0, 0.0]), 0.2), [0.5, 0.65, 0.2])


def test_rc_lb_nmpc_keeps_its_turn_commands_within_what_the_drive_can_follow():
    """Coming into the arc with the drive not turning yet, the plan asks for the turn at once; with the
    limit known, every command of the plan leads the drive's modelled state by at most limit x tau."""
    path = arc_path()
    wide = Corridor(path.s, 1.0, math.radians(60))
    ctx = dataclasses.replace(ctx_for(path, path.pose_at(9.0) + np.array([0.0, -0.15, 0.0]), v=1.0, corridor=wide),
                              xi_now=(1.0, 0.0), xi_capture=(1.0, 0.0))
    free_settings = NMPCSettings(sqp_iter=10, actuator_tau_s=(0.3, 0.4))
    free = RCLBNMPCLaw(free_settings, DT)
    free.angular(ctx)
    leads_free = TurnLead(math.exp(-DT / 0.4), 0.2).leads(free.last_step.result.iterate.w, 0.0)
    assert np.max(np.abs(leads_free)) > 0.3                               # unlimited, it asks for more
    law = RCLBNMPCLaw(dataclasses.replace(free_settings, turn_accel_max_radps2=0.5), DT)
    res = law.angular(ctx)
    it = law.last_step.result.iterate
    leads = law.turn_lead.leads(it.w, 0.0)
    assert law.turn_lead.max_radps == pytest.approx(0.2)
    assert np.all(np.abs(leads) <= 0.2 + 1e-4), leads
    assert res.w_radps > 0.1 and not res.stop_reason                     # it still turns towards the route


def test_the_limit_is_kept_on_disk_per_nominal_model(tmp_path, caplog):
    from services.controller import turn_accel_file
    turn_accel_file.save(tmp_path, "unicycle-tauw317ms", 0.9)
    assert turn_accel_file.load(tmp_path, "unicycle-tauw317ms") == 0.9
    assert turn_accel_file.load(tmp_path, "unicycle-other") is None                  # none stored
    turn_accel_file.file_of(tmp_path, "unicycle-tauw317ms").write_bytes(b"\x93not a record")
    with caplog.at_level("WARNING"):
        assert turn_accel_file.load(tmp_path, "unicycle-tauw317ms") is None
    assert "read again from the next repeat" in caplog.text
    with pytest.raises(ValueError):
        turn_accel_file.TurnAccelRecord(model_tag="m", limit_radps2=math.inf)


def test_a_record_filed_under_another_models_name_is_not_used(tmp_path, caplog):
    """per_model_file.load checks the record's own model, not only its file name."""
    from services.controller import turn_accel_file
    theirs = turn_accel_file.save(tmp_path, "unicycle-other", 1.5)
    theirs.rename(turn_accel_file.file_of(tmp_path, "unicycle-tauw317ms"))
    with caplog.at_level("WARNING"):
        assert turn_accel_file.load(tmp_path, "unicycle-tauw317ms") is None
    assert "is of model unicycle-other" in caplog.text
