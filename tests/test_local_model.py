"""The local window the NMPC laws draw their GP from (services/controller/local_model.py): which speed
bin it is drawn at, with and without hysteresis, against the window requests a fake store records."""
import numpy as np

from common.messages import HyperDim, HyperMsg
from common.path import Path
from services.controller.laws import StepContext
from services.controller.local_model import LocalModels

V_BIN = 0.25


def straight():
    s = np.arange(0.0, 20.0, 0.25)
    return Path("straight", np.column_stack([s, np.zeros_like(s), np.zeros_like(s)]))


def ctx(path, v):
    return StepContext(now_s=0.0, path=path, vertex=4, pose=np.array([1.0, 0.0, 0.0]), s_m=1.0, e_lat_m=0.0,
                       e_head_rad=0.0, v_mps=v, speed_at=lambda _s: v, prev_cmd=(v, 0.0), prev_pose=None,
                       w_limit=2.0, w_limit_at=lambda _v: 2.0, pose_cov=None, corridor=None, v_max_mps=2.0)


class Store:
    """Windows by speed bin: experiences only in `filled` bins; records the bins asked for."""

    def __init__(self, filled):
        self.filled = set(filled)
        self.asked = []
        rng = np.random.default_rng(0)
        self.A, self.G = rng.normal(size=(12, 9)), 0.01 * rng.normal(size=(12, 3))

    def window(self, vertex, speed):
        b = int(np.floor(speed / V_BIN))
        self.asked.append(b)
        return (self.A, self.G) if b in self.filled else (np.zeros((0, 9)), np.zeros((0, 3)))


def hyper():
    dim = HyperDim(lengthscales=[1.0] * 9, signal_std=0.01, noise_std=0.001)
    return HyperMsg(stamp_s=1.0, path_id="straight", version=1, n_used=12, n_total=12, fit_s=0.1, lml=[0.0] * 3,
                    dims=[dim, dim, dim])


def test_without_hysteresis_the_window_follows_the_speed_every_step():
    path, store = straight(), Store(range(10))
    models = LocalModels(store.window, hyper, 1.0, V_BIN)
    for v in (0.70, 0.80, 0.70, 0.80):
        models.model_for(ctx(path, v))
    assert store.asked == [2, 3, 2, 3]


def test_with_hysteresis_a_speed_at_a_bin_edge_keeps_one_window():
    path, store = straight(), Store(range(10))
    models = LocalModels(store.window, hyper, 1.0, V_BIN, hold_steps=5)
    for v in (0.70, 0.80, 0.70, 0.80, 0.70, 0.80, 0.70):
        models.model_for(ctx(path, v))
    assert store.asked == [2] * 7
    # staying in the neighbouring bin for hold_steps calls moves the window there
    for _ in range(5):
        models.model_for(ctx(path, 0.80))
    assert store.asked[7:] == [2, 2, 2, 2, 3]
    # a jump of two bins or more moves it at once
    models.model_for(ctx(path, 1.30))
    assert store.asked[-1] == 5


def test_with_hysteresis_an_empty_window_falls_back_to_the_last_one_with_experience():
    path, store = straight(), Store({7, 8})
    models = LocalModels(store.window, hyper, 1.0, V_BIN, hold_steps=5)
    assert models.model_for(ctx(path, 1.9)) is not None and store.asked == [7]
    gp = models.model_for(ctx(path, 0.3))            # slowed far below where it has driven here
    assert store.asked[1:] == [1, 7] and gp is not None
    nothing = LocalModels(store.window, hyper, 1.0, V_BIN)
    nothing.model_for(ctx(path, 1.9))
    assert nothing.model_for(ctx(path, 0.3)) is None     # the thesis's window: no experience, no model


def test_the_window_at_another_speed_is_drawn_at_its_own_bin_and_leaves_the_held_bin_alone():
    """A law that slowed tests the asked speed on the window of that speed's bin (speed_ladder.py): drawn
    around where a plan at that speed goes, without moving the bin the law's own window holds; nothing
    where that bin has no experience or is the law's own."""
    path, store = straight(), Store({2, 8})
    models = LocalModels(store.window, hyper, 1.0, V_BIN, hold_steps=5)
    slow = models.model_for(ctx(path, 0.6))
    fast = models.model_at(ctx(path, 0.6), 2.1)
    assert store.asked == [2, 8] and fast is not None and fast is not slow
    models.model_for(ctx(path, 0.8))                  # one call in the neighbouring bin: the window holds
    assert store.asked[-1] == 2
    assert models.model_at(ctx(path, 0.6), 1.4) is None      # no experience at 1.4
    assert models.model_at(ctx(path, 0.6), 0.7) is None      # the law's own window's bin
    assert LocalModels(store.window, lambda: None, 1.0, V_BIN).model_at(ctx(path, 0.6), 2.1) is None


def test_prepare_builds_the_next_steps_window_so_the_step_does_not():
    """The node calls `prepare` after publishing a command: the window GP where the robot will be next is
    built then, and the next step finds it (no build inside the step); a step that ends up elsewhere
    builds its own, as before."""
    import dataclasses
    path, store = straight(), Store(range(10))
    for hold in (0, 5):
        models = LocalModels(store.window, hyper, 1.0, V_BIN, hold_steps=hold)
        here = ctx(path, 0.8)
        first = models.model_for(here)
        assert models.builds == 1 and first is not None
        nxt = dataclasses.replace(here, s_m=here.s_m + 0.3)              # the next window's centre vertex
        assert models.center_vertex(nxt) != models.center_vertex(here)
        models.prepare(path, nxt.s_m, 0.8)
        assert models.builds == 2 and models.prepared == 1
        gp = models.model_for(nxt)
        assert models.builds == 2 and gp is not None and gp is not first
        models.model_for(dataclasses.replace(here, s_m=here.s_m + 2.0))   # not prepared: built in the step
        assert models.builds == 3 and models.prepared == 1


def test_the_windows_model_fades_below_the_slowest_speed_its_experiences_rolled_at():
    path, store = straight(), Store(range(10))
    model = LocalModels(store.window, hyper, 1.0, V_BIN).model_for(ctx(path, 0.7))
    assert model.v_floor == np.percentile(np.abs(store.A[:, 3]), 10.0) > 0.0
    a = store.A[0].copy()
    a[3] = 0.5 * model.v_floor
    np.testing.assert_allclose(model.mean(a[None])[0], 0.5 * model.gp.mean(a[None])[0])
