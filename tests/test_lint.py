"""The lint: ``ruff check`` of the whole repository is clean, in the ROS 2 Python style.

ruff.toml holds the rules of ament_flake8 (what ``colcon test`` checks in a ROS 2 package):
pycodestyle and pyflakes, pydocstyle's pep257 convention with ament's ignores, single quotes,
99 columns. The second test keeps that subset from being weakened without notice.
"""

import importlib.util
import pathlib
import re
import subprocess
import sys
import tomllib

import pytest

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
CONFIG = REPO_ROOT / 'ruff.toml'

pytestmark = pytest.mark.skipif(importlib.util.find_spec('ruff') is None,
                                reason='ruff is not installed in this interpreter '
                                       '(requirements.txt pins it: run scripts/setup)')

# What ament_flake8 checks, by ruff code: examples of each family, and what it leaves out.
CHECKED = ('E101', 'E117', 'E225', 'E231', 'E302', 'E303', 'E501', 'E711', 'W291', 'W391',
           'W605', 'F401', 'F811', 'F841',
           'D200', 'D205', 'D209', 'D210', 'D300', 'D301', 'D400', 'D401', 'D403',
           'Q000', 'Q001', 'Q002', 'Q003',
           # codes that the code's noqa comments cite
           'E402', 'E731', 'E741', 'BLE001', 'PLW0603', 'SIM115', 'S506')
NOT_CHECKED = ('D100', 'D101', 'D102', 'D103', 'D104', 'D105', 'D106', 'D107', 'D203',
               'D212', 'D404', 'PLC0415')


def ruff(*args):
    return subprocess.run([sys.executable, '-m', 'ruff', *args], cwd=REPO_ROOT,
                          capture_output=True, text=True, timeout=300)


def test_ruff_check_is_clean():
    result = ruff('check', '--no-cache', '--output-format', 'concise', str(REPO_ROOT))
    assert result.returncode == 0, (
        f'ruff check found problems (fix them, or see ruff.toml):\n{result.stdout}'
        f'{result.stderr}')


def test_the_config_is_the_ament_flake8_subset():
    config = tomllib.loads(CONFIG.read_text(encoding='utf-8'))
    assert config['line-length'] == 99
    assert config['target-version'] == 'py311'
    assert set(config['extend-exclude']) == {'ros_ws/build', 'ros_ws/install', 'ros_ws/log',
                                             '.venv'}
    lint = config['lint']
    assert lint['pydocstyle']['convention'] == 'pep257'
    assert lint['flake8-quotes']['inline-quotes'] == 'single'
    for pattern, codes in lint.get('per-file-ignores', {}).items():
        assert 'ALL' not in codes, f'every rule is off for {pattern}'
    # The rules in force, as ruff resolves them for a module of the code.
    result = ruff('check', '--no-cache', '--show-settings',
                  str(REPO_ROOT / 'ros_ws/src/wip_control/wip_control/core/model.py'))
    assert result.returncode == 0, result.stderr
    block = re.search(r'^linter\.rules\.enabled = \[\n(.*?)^\]', result.stdout,
                      re.MULTILINE | re.DOTALL)
    assert block, result.stdout[:2000]
    enabled = set(re.findall(r'\(([A-Z]+[0-9]+)\)', block.group(1)))
    assert not set(CHECKED) - enabled, f'not checked: {sorted(set(CHECKED) - enabled)}'
    assert not set(NOT_CHECKED) & enabled, f'checked: {sorted(set(NOT_CHECKED) & enabled)}'
