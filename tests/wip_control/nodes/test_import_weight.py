"""A controller process does not load the simulator's compiled plant, nor SciPy to import.

numba and llvmlite (the plant's RK4, ``core.plant_rk4``) cost about 0.2 s of import and
60 MB of memory per process (measured: the six composed nodes built, 102 MB against 162 MB
resident); the controllers never step a plant, and on a robot's small computer the
separate layout starts six such processes. A plant built in a process loads it. SciPy
(about 0.2 s of CPU) is loaded where a matrix function is computed, at the construction of
an observer or an LQR: the ARC, MPC, mixer, reference and generator processes never do.
"""

import subprocess
import sys

import pytest

pytest.importorskip('rclpy')

pytestmark = pytest.mark.ros

_PROGRAM = """
import sys
import {module}
print('numba' in sys.modules, 'llvmlite' in sys.modules, 'scipy' in sys.modules)
"""


@pytest.mark.parametrize('module', [
    'wip_control.nodes.controllers', 'wip_control.nodes.eso_node',
    'wip_control.nodes.mpc_node', 'wip_control.nodes.torque_mixer_node'])
def test_the_controller_nodes_do_not_import_numba(module):
    done = subprocess.run([sys.executable, '-c', _PROGRAM.format(module=module)],
                          capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ['False', 'False', 'False'], done.stdout


def test_a_plant_loads_its_compiled_integrator():
    program = _PROGRAM.format(module='wip_sim.core.plant') + """
from wip_description.params import ModelParams
plant = wip_sim.core.plant.Plant(ModelParams())
print('numba' in sys.modules)
"""
    done = subprocess.run([sys.executable, '-c', program], capture_output=True, text=True,
                          timeout=300, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ['False', 'False', 'False', 'True'], done.stdout
