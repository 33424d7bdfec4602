"""Run by test_harness.py, not collected: each test appends its worker and DDS domain."""

import os

import pytest


@pytest.mark.parametrize('k', range(8))
def test_write_the_domain(k):
    with open(os.environ['WIP_DOMAIN_PROBE'], 'a', encoding='utf-8') as out:
        out.write(f"{os.environ.get('PYTEST_XDIST_WORKER')} {os.environ['ROS_DOMAIN_ID']}\n")
