"""The stop's steering (brake.py): the roll-out distance against closed forms, and the offset that weighs
the corridor's lateral and heading limits."""
import math

import pytest

from bench.stops import stops_on
from services.controller.actuator import ActuatorLag
from services.controller.brake import balanced_offset, roll_out_m


def test_without_a_lag_the_robot_rolls_the_sum_of_its_braking_commands():
    # 1.0, 0.75, 0.5, 0.25 m/s for a period each, then 0
    assert roll_out_m(ActuatorLag(), (1.0, 0.0), 1.0, 2.5, 0.1, 0.03) == pytest.approx(0.25)


def test_a_lagging_drive_commanded_to_stop_rolls_its_speed_times_its_time_constant():
    # first-order lag from 1 m/s, command 0 at once: the integral of exp(-t / tau) is tau (to 0.03 / 1)
    d = roll_out_m(ActuatorLag(0.5, 0.0, 0.1), (1.0, 0.0), 0.0, math.inf, 0.1, 0.03)
    assert d == pytest.approx(0.5, rel=0.035)


def test_on_the_route_and_aligned_it_steers_the_routes_own_curvature():
    assert balanced_offset(0.0, 0.0, 1.0, -0.3, 0.3, math.radians(15), 0.5) == 0.0


def test_left_of_the_route_it_turns_right_until_the_heading_takes_as_much_of_its_limit():
    lat, d, limit = 0.2, 1.2, math.radians(10)
    D = balanced_offset(lat, 0.0, d, -0.25, 0.25, limit, 0.5)
    assert D < 0
    # at the end of the roll-out neither error takes more of its limit than the lateral took at the stop
    end_lat, end_head = lat + 0.5 * D * d * d, D * d
    assert max(abs(end_lat) / 0.25, abs(end_head) / limit) <= lat / 0.25 + 1e-9
    # a tighter heading limit buys less lateral correction
    assert abs(balanced_offset(lat, 0.0, d, -0.25, 0.25, math.radians(4), 0.5)) < abs(D)


def test_a_grizzly_stopped_in_a_corner_inside_its_corridor_stays_inside():
    """`lbc bench stops`'s case with a 0.5 m / 10 deg corridor: a Grizzly stopped at 1.9 m/s in the
    middle of an 8 m corner, 0.92 of its corridor taken. Steering back as FL does (its lateral term
    grows like 1 / v^2) took it to 1.17; weighing both limits, it stays at 0.92."""
    (out,) = stops_on("grizzly", 8.0, [0.75], [0.5], seed=3, corridor=(0.5, 10.0))
    assert out.share_at_stop < 1.0
    assert out.share_max <= out.share_at_stop + 0.02
