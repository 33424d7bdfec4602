"""One number check: a scenario key, a node parameter, a command-line option, the robot's model.

``wip_runtime.config.check_number`` decides; each reader words the refusal its own way.
"""

import argparse
import math

import pytest

from wip_description.params import ModelParams
from wip_runtime.cli import bounded
from wip_runtime.config import check_number, ParamError

RANGE = {'minimum': 0.0, 'maximum': 10.0, 'exclusive_minimum': True}


@pytest.mark.parametrize('value', [1e-9, 0.5, 10.0, 3])
def test_a_number_in_range_passes_every_reader(value):
    assert check_number('x', value, RANGE, want_int=False) == float(value)
    assert bounded(float, 0.0, 10.0, exclusive_minimum=True)(repr(value)) == float(value)


@pytest.mark.parametrize('value', [0.0, -1.0, 10.5, math.inf, -math.inf, math.nan])
def test_a_number_out_of_range_is_refused_by_every_reader(value):
    with pytest.raises(ParamError):
        check_number('x', value, RANGE, want_int=False)
    with pytest.raises(argparse.ArgumentTypeError):
        bounded(float, 0.0, 10.0, exclusive_minimum=True)(repr(value))


def test_the_command_line_keeps_its_words():
    with pytest.raises(argparse.ArgumentTypeError, match=r'^must be >= 0 and <= 99, got 100$'):
        bounded(int, 0, 99)('100')
    with pytest.raises(argparse.ArgumentTypeError, match="^'nan' is not a finite number$"):
        bounded(float, 0.0)('nan')
    with pytest.raises(argparse.ArgumentTypeError, match="^'1.5' is not an integer$"):
        bounded(int, 0, 99)('1.5')
    assert bounded(int, 0, 99)('7') == 7 and isinstance(bounded(int, 0, 99)('7'), int)


@pytest.mark.parametrize('name, value', [('body_mass', 0.0), ('wheel_radius', -0.1),
                                         ('gravity', math.nan), ('track_width', math.inf),
                                         ('yaw_inertia', True)])
def test_the_robot_model_refuses_what_is_not_a_positive_finite_number(name, value):
    with pytest.raises(ParamError, match=f'^ModelParams.{name}: '):
        ModelParams(**{name: value})


def test_an_int_too_large_for_a_float_is_refused_in_one_line_not_overflowed():
    # float(10**400) raises OverflowError: a scenario key or campaign value written as a
    # 400-digit integer gets the one-line error instead.
    with pytest.raises(ParamError, match='duration: out of range'):
        check_number('duration', 10 ** 400, {}, want_int=False)
    assert check_number('seed', 10 ** 400, {}, want_int=True) == 10 ** 400


def test_the_scenario_scalars_and_the_campaign_values_use_the_one_check():
    from wip_control.core.controller_settings import checked_scalar
    from wip_tools.campaign_file import _number, CampaignError
    with pytest.raises(ParamError, match='control_rate: expected an integer'):
        checked_scalar('control_rate', 2.5, int)
    with pytest.raises(ParamError, match='out of range'):
        checked_scalar('duration', 10 ** 400, float)
    with pytest.raises(CampaignError, match='campaign.vary.x: must be finite'):
        _number(float('nan'), 'campaign.vary.x')
    assert checked_scalar('duration', 3, float) == 3.0 and _number(2, 'x') == 2.0
