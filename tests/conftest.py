"""Test configuration: jaxdem's process-wide settings (float64, one OpenBLAS thread, the
compilation cache: jaxdem.config.configure, as the command line makes them), the shared
scene builders on the path, hypothesis profiles.

Hypothesis profiles (used by tests/test_properties.py):

- ``ci`` (default): few examples, derandomized (reproducible), no shrinking, no example
  database, so that CI runs the same scenes every time in about a minute.
- ``long``: ``pytest --robust-long`` or ``JAXDEM_HYPOTHESIS=long``: 200 random examples
  per property, shrinking on (``--hypothesis-seed=N`` replays a run).
"""

import os
import sys
from pathlib import Path

from hypothesis import HealthCheck, Phase, settings

from jaxdem import config as jaxdem_config

jaxdem_config.configure()
sys.path.insert(0, str(Path(__file__).parent))

# Each example is a whole solve (seconds, a JAX compilation for each new shape): no
# per-example deadline, and the health checks about slow data generation are moot.
_SLOW = [HealthCheck.too_slow, HealthCheck.data_too_large]
settings.register_profile(
    "ci", max_examples=6, deadline=None, derandomize=True, database=None,
    phases=[Phase.explicit, Phase.generate], suppress_health_check=_SLOW, print_blob=True)
settings.register_profile(
    "long", max_examples=200, deadline=None, suppress_health_check=_SLOW, print_blob=True)


def pytest_addoption(parser):
    parser.addoption("--robust-long", action="store_true", default=False,
                     help="run the property-based tests (tests/test_properties.py) with the "
                          "long hypothesis profile (also: JAXDEM_HYPOTHESIS=long)")


def pytest_configure(config):
    long = config.getoption("--robust-long") or os.environ.get("JAXDEM_HYPOTHESIS") == "long"
    settings.load_profile("long" if long else "ci")
