"""Fixtures of the process-level bag tool tests (recorder, replayer).

A fixture lives here, not in bagtools_helpers.py: a test module that imported it from there
would shadow the import with the test's parameter of the same name (pyflakes F811).
"""

import pytest


@pytest.fixture
def tools():
    """Yield started tools; killed at the end even when a test fails."""
    started = []
    yield started
    for tool in started:
        if tool.process.poll() is None:
            tool.process.kill()
            tool.process.communicate()
