"""`lbc bench stops` prints its JSON on the last line and refuses a grid it cannot drive."""
import json

import pytest

from bench import stops


def test_one_husky_stop_prints_the_documented_keys(capsys):
    assert stops.main(["--robots", "husky", "--radii", "5", "--speeds", "0.5", "0.9", "--at", "0.5"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    husky = result["presets"]["husky"]
    assert result["stops"] == husky["stops"] == 2
    assert set(husky) >= {"heading_turned_deg_median", "heading_turned_deg_max", "lateral_growth_m_max",
                          "rolled_m_median", "worst_turn", "worst_lateral"}
    # a Husky's drive settles within a period: from 0.5 m/s it rolls a few centimetres, turning < 2 deg
    assert 0.0 < husky["rolled_m_median"] < 0.1 and husky["heading_turned_deg_max"] < 2.0


def test_the_side_slope_lies_under_the_whole_corner_and_the_json_says_so(capsys):
    from services.bridge.terrain import footprint
    for radius in (5.0, 8.0):
        (patch,) = stops.corner_slope(radius, 12.0, -90.0)
        arc = stops.corner_route(radius)[2:]
        assert all(footprint(patch, x, y) == 1.0 for x, y in arc)     # the full tilt all round the arc
    assert stops.corner_slope(5.0, 0.0, -90.0) == []
    assert stops.main(["--robots", "husky", "--radii", "5", "--speeds", "0.5", "--at", "0.5", "--slope", "12"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (result["slope_deg"], result["downhill_deg"], result["stops"]) == (12.0, -90.0, 1)


@pytest.mark.parametrize("bad", [["--speeds", "1.5"], ["--at", "-0.1"], ["--radii", "0"], ["--slope", "50"]])
def test_a_grid_outside_its_range_is_refused(bad, capsys):
    with pytest.raises(SystemExit) as exc:
        stops.main(bad)
    assert exc.value.code == 2 and "speeds in (0, 1]" in capsys.readouterr().err
