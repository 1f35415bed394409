"""The suite's own rules (``conftest.py``): the fast tier and the core suite start no DDS, markers
follow the fixtures a test uses, graphs of tests never share a ROS domain."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from conftest import DOMAINS, lease_domain

BIN = Path(sys.executable).parent


def test_a_test_without_the_ros_marker_cannot_start_dds():
    """An rclpy context made, or a node process started, by a test without ``@pytest.mark.ros``
    fails that test, naming the marker (the fast tier would otherwise start DDS unnoticed)."""
    from rclpy.context import Context
    with pytest.raises(AssertionError, match=r"test_suite\.py::.* initialises an rclpy context but is not marked "
                                             r"@pytest\.mark\.ros"):
        Context().init()
    with pytest.raises(AssertionError, match=r"starts the node process .*plant_sim but is not marked"):
        subprocess.Popen([str(BIN / "plant_sim"), "--ros-args"])
    out = subprocess.run([sys.executable, "-c", "print(1)"], capture_output=True, text=True, timeout=60)
    assert out.stdout == "1\n"                                         # any other process starts


def test_markers_follow_the_fixtures(request, shared_data):
    """A test using the shared data is ``realdata`` without saying so (``-m "not realdata"``
    deselects it)."""
    assert request.node.get_closest_marker("realdata") is not None
    assert request.node.get_closest_marker("ros") is None and request.node.get_closest_marker("slow") is None


@pytest.mark.ros
def test_ros_tests_are_slow_too(request):
    """The fast tier (``-m "not slow"``) deselects every ``ros`` test."""
    assert request.node.get_closest_marker("slow") is not None


def test_each_lease_is_a_domain_no_other_lease_holds():
    with lease_domain() as a, lease_domain() as b:
        assert a != b and a in DOMAINS and b in DOMAINS
        code = ("import sys; sys.path.insert(0, 'test'); from conftest import lease_domain\n"
                "with lease_domain() as d: print(d)")
        other = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                               cwd=Path(__file__).parents[1])
        assert other.returncode == 0, other.stderr
        assert int(other.stdout) not in (a, b)                 # another process (an xdist worker, a checkout)


@pytest.mark.slow            # a pytest collection in a subprocess: ~10 s
def test_parallel_runs_start_with_the_longest_work_and_make_each_shared_fixture_once():
    """Under ``pytest -n`` the tests sharing the EMPS diagnosis are handed out first, as one group
    (one worker makes the fixture), then the slow tests, then the fast tier: collected in that
    order whatever the files' order."""
    root = Path(__file__).parents[1]
    code = ("import sys, pytest\n"
            "class P:\n"
            "    def pytest_collection_finish(self, session):\n"
            "        for it in session.items:\n"
            "            g = it.get_closest_marker('xdist_group')\n"
            "            print('ITEM', it.nodeid, 'slow' if it.get_closest_marker('slow') else 'fast',"
            " g.args[0] if g else '-')\n"
            "sys.exit(pytest.main(['--collect-only', '-q', '-p', 'no:cacheprovider', 'test/test_suite.py',"
            " 'test/test_diagnosis_emps.py', 'test/test_diagnosis_executor.py'], plugins=[P()]))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=root)
    assert out.returncode == 0, out.stdout + out.stderr
    rows = [line.split()[1:] for line in out.stdout.splitlines() if line.startswith("ITEM ")]
    n_emps = sum(r[2] == "emps_diagnosis" for r in rows)
    assert n_emps >= 3 and all(r[2] == "emps_diagnosis" for r in rows[:n_emps])   # one group, first
    assert all(r[0].startswith("test/test_diagnosis_emps.py") for r in rows[:n_emps])
    ranks = [0 if i < n_emps else (1 if r[1] == "slow" else 2) for i, r in enumerate(rows)]
    assert ranks == sorted(ranks)                                      # slow before fast after the group
    dask = [r for r in rows if "dask_local_cluster" in r[0]]
    assert dask and all(r[2] == "dask_cluster" for r in dask)


@pytest.mark.xdist_group("suite_grouping")
def test_groups_are_handed_to_one_worker_under_loadgroup(request):
    """Under ``pytest -n --dist loadgroup`` (the README's test command) each ``xdist_group`` -- this
    test's own, and those ``conftest`` gives the tests sharing the EMPS diagnosis or the Dask
    cluster -- is one scheduling unit: pytest-xdist suffixes the node ids with ``@group``. It did
    not, and every worker made the EMPS diagnosis itself: with pytest 9.2 and pytest-xdist 3.8 the
    suffix went to an attribute pytest 9 no longer reads, and conftest's marks came after
    pytest-xdist's hook had read them. Skipped outside that mode."""
    if not getattr(request.config.option, "loadgroup", False):      # set on xdist's workers
        pytest.skip("not run under pytest -n --dist loadgroup")
    grouped = [(it.nodeid, it.get_closest_marker("xdist_group").args[0]) for it in request.session.items
               if it.get_closest_marker("xdist_group") is not None]
    assert request.node.nodeid.endswith("@suite_grouping"), request.node.nodeid
    bad = [nid for nid, g in grouped if not nid.endswith("@" + g)]
    assert not bad, bad
