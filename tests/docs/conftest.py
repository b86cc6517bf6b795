"""The site's browser test records its screenshot's path (``record_property("screenshot", ...)``); the run's
summary prints it, also when pytest-xdist ran the test on a worker (the property travels with the report)."""

_SCREENSHOTS: list = []


def pytest_runtest_logreport(report):
    if report.when == "call":
        _SCREENSHOTS.extend(value for name, value in report.user_properties if name == "screenshot")


def pytest_terminal_summary(terminalreporter):
    for path in _SCREENSHOTS:
        terminalreporter.write_line(f"documentation site screenshot: {path}")
