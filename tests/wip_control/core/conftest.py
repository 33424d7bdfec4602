"""Fixtures of the core's tests."""

import pytest

from wip_control.core.safety import SafetyMonitor


@pytest.fixture(params=['interpreted', 'compiled'])
def safety_tick(request, monkeypatch):
    """Every SafetyMonitor of the test interpreted, then with the compiled steady tick."""
    if request.param == 'compiled':
        made = SafetyMonitor.__init__
        checking = []   # use_compiled makes scratch monitors of its own: not those

        def init(self, *args, **kwargs):
            made(self, *args, **kwargs)
            if not checking:
                checking.append(self)
                try:
                    assert self.use_compiled() == ''
                finally:
                    checking.clear()
        monkeypatch.setattr(SafetyMonitor, '__init__', init)
    return request.param
