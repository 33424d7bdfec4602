"""The compiled kernels of the controllers kept fresh (core/compiled.py).

numba's cache knows only a kernel file's date: a formula changed in a module whose
functions the kernel compiles (``register_jitable``: retiming.py, slip.py...) would be served
stale (measured: the old floats, silently). The digest of the sources beside the cache
decides.
"""

import os
import pathlib
import sys

import pytest

from wip_control.core import attitude_kernel, estimator_kernel, retiming_kernel, safety_kernel


@pytest.mark.parametrize('module, kernel', [(retiming_kernel, 'sample'),
                                            (estimator_kernel, 'step'),
                                            (safety_kernel, 'tick'),
                                            (attitude_kernel, 'attitude')])
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


@pytest.mark.parametrize('module', [retiming_kernel, estimator_kernel, safety_kernel,
                                    attitude_kernel])
def test_the_digest_covers_every_file_whose_functions_the_kernel_compiles(monkeypatch,
                                                                          module):
    # A formula changed in any of them (model.py's input gains, say) gives another digest.
    files = ({pathlib.Path(sys.modules[f.__module__].__file__)
              for f in module.COMPILED_FUNCTIONS} | {pathlib.Path(module.__file__)}
             | {pathlib.Path(m.__file__) for m in getattr(module, 'ALSO_COMPILED', ())})
    assert len(files) >= 2
    before = module.sources_digest()
    read_bytes = pathlib.Path.read_bytes
    for changed in files:
        monkeypatch.setattr(pathlib.Path, 'read_bytes', lambda self, changed=changed: (
            read_bytes(self) + b'#' if self == changed else read_bytes(self)))
        assert module.sources_digest() != before, changed
        monkeypatch.setattr(pathlib.Path, 'read_bytes', read_bytes)
    assert module.sources_digest() == before
    assert 'model' in {f.__module__.rsplit('.', 1)[-1] for f in
                       estimator_kernel.COMPILED_FUNCTIONS}
