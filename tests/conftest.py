import os

from hypothesis import HealthCheck, settings

settings.register_profile("softrtc", deadline=None, max_examples=60,
                          suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "softrtc"))

# Compiled programs ([KC-1]) go to a folder of this checkout's test cache, not the user's: a run of the
# tests neither reads programs another checkout or version left in ~/.cache nor leaves its own there.
# Set SOFTRTC_JAX_CACHE to choose another folder (or "off").
os.environ.setdefault("SOFTRTC_JAX_CACHE",
                      os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), ".pytest_cache",
                                   "softrtc-jax"))


def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist, files holding a test marked ``slow`` come first, each file's tests in their order.

    `make test` hands whole files to two workers in collection order: the long files started first leave
    the short ones to fill both workers at the end instead of one long file running on alone. A run in one
    process keeps pytest's order.
    """
    if not hasattr(config, "workerinput"):
        return
    slow = {item.path for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: item.path not in slow)  # stable: file order and test order otherwise kept


# The one skip that SOFTRTC_REQUIRE_ALL=1 tolerates: the benchmark levels are data outside this
# repository. Tests skip with exactly this reason; any other skip (a missing package) fails the run.
SHARED_LEVELS_REASON = "needs the benchmark levels in ../shared/kinetix-levels"


def tolerated_skip(longrepr) -> bool:
    """Whether a skipped test's report carries exactly :data:`SHARED_LEVELS_REASON`."""
    message = longrepr[2] if isinstance(longrepr, tuple) and len(longrepr) == 3 else str(longrepr)
    return message == f"Skipped: {SHARED_LEVELS_REASON}"


def pytest_sessionfinish(session, exitstatus):
    """With SOFTRTC_REQUIRE_ALL=1 (set by `make test`) a skipped test fails the run.

    The tests skip when an optional dependency is missing so that a partial
    install can still run the rest; the full install must run everything.
    Only the benchmark levels, data outside this repository, may be absent.
    Under pytest-xdist the controller decides: it receives every worker's
    reports, and a worker's exit status does not reach the run's.
    """
    if os.environ.get("SOFTRTC_REQUIRE_ALL") != "1" or hasattr(session.config, "workerinput"):
        return
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    skipped = reporter.stats.get("skipped", []) if reporter is not None else []
    missing = [r for r in skipped if not tolerated_skip(r.longrepr)]
    if missing:
        for r in missing:
            reporter.write_line(f"SOFTRTC_REQUIRE_ALL: skipped {r.nodeid or r.fspath}: {r.longrepr}", red=True)
        session.exitstatus = 1
