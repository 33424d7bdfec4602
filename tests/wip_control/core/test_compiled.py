"""The compiled kernels of the controllers kept fresh (core/compiled.py).

numba's cache knows only a kernel file's date: a formula changed in a module whose
functions the kernel compiles (``register_jitable``: retiming.py, slip.py...) would be served
stale (measured: the old floats, silently). The digest of the sources beside the cache
decides.
"""

import os
import pathlib

import pytest

from wip_control.core import estimator_kernel, retiming_kernel


@pytest.mark.parametrize('module, kernel', [(retiming_kernel, 'sample'),
                                            (estimator_kernel, 'step')])
def test_a_kernel_is_compiled_afresh_when_the_sources_it_compiles_change(monkeypatch, module,
                                                                         kernel):
    refreshed = []
    monkeypatch.setattr(module, 'refresh', lambda: refreshed.append(True))
    name = f'{module.__name__}.sources.test-{os.getpid()}'
    monkeypatch.setattr(module, 'SOURCES_STAMP', name)
    stamp = pathlib.Path(getattr(module, kernel).stats.cache_path) / name
    try:
        module.warm_up()     # no digest kept: compiled afresh, the digest written
        assert refreshed == [True]
        assert stamp.read_text(encoding='utf-8') == module.sources_digest()
        module.warm_up()     # the same sources: the cache is used
        assert refreshed == [True]
        monkeypatch.setattr(module, 'sources_digest', lambda: 'a formula changed')
        module.warm_up()
        assert refreshed == [True, True]
        assert stamp.read_text(encoding='utf-8') == 'a formula changed'
    finally:
        stamp.unlink(missing_ok=True)
