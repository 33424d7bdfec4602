"""scripts/soak: the path-distance closed forms and the one-line usage errors.

The long real-time runs themselves are measured by the tool, not in the suite.
"""

import math

import numpy as np
import pytest

from wip_tools.soak import CIRCLE_RADIUS, distance_to_path, main, scenario_for


def test_distance_to_the_line_and_to_the_circle_are_the_closed_forms():
    x = np.array([0.0, 3.0, -1.0])
    y = np.array([0.2, -0.5, 0.0])
    assert distance_to_path('line', x, y).tolist() == [0.2, 0.5, 0.0]
    # On the circle: zero; at the centre: the radius; outside: r - R.
    angle = np.linspace(0.0, 2 * math.pi, 7)
    on = distance_to_path('circle', CIRCLE_RADIUS * np.cos(angle), CIRCLE_RADIUS * np.sin(angle))
    assert np.allclose(on, 0.0, atol=1e-12)
    assert distance_to_path('circle', np.array([0.0]), np.array([0.0]))[0] == CIRCLE_RADIUS
    assert distance_to_path('circle', np.array([3.0]), np.array([4.0]))[0] == \
        pytest.approx(5.0 - CIRCLE_RADIUS)


def test_the_circle_scenario_is_the_circle_the_distance_is_measured_to():
    reference = scenario_for('circle')['reference']
    assert reference['kind'] == 'circle' and reference['circle_radius'] == CIRCLE_RADIUS
    assert scenario_for('line')['reference']['kind'] == 'line'


@pytest.mark.parametrize('argv, message', [
    (['--runs', '0'], 'need --runs >= 1'),
    (['--seconds', '10'], 'need --runs >= 1 and --seconds > 15'),
    (['--seconds', 'nan'], 'need --runs >= 1'),
    (['--freeze', '-5'], '--freeze durations must be in (0, 10000) ms'),
])
def test_bad_options_are_one_line_usage_errors(argv, message, capsys, tmp_path):
    assert main(argv + ['--out', str(tmp_path / 'out')]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err
    assert not (tmp_path / 'out').exists()   # nothing written
